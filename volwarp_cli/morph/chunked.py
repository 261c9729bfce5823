"""The morph by blocks: frames from fields kept on disk, computed and written block by block.

For a morph whose fields do not fit in memory (``volwarp morph --chunked``,
or when the in-memory morph does not fit the budget). Each shape's signed
distance field is computed out of core, once
(:func:`volwarp_cli.distance.operation.field_operation` on the executor: the
exact passes, or a band with ``max_distance``), into a float32 scratch file;
the frames are then :func:`.frames.frames` of those files, as in memory of
arrays (each frame an operation whose blocks need their own box of both
fields and nothing more), so they equal the in-memory frames bit for bit,
their meshes byte for byte.

Inputs on other grids than the frame grid, and affine alignments, run by
blocks too: each field is computed by blocks on its own input's grid, as
above, then resampled onto the frame grid block by block into a second
scratch file (:func:`resampled`), each frame-grid block reading only
the box of the field its voxels' coordinates reach
(:func:`.interpolate.needed_box`: the hull of the block's 8 corners' images
plus the trilinear support, clipped to the input) through the very function
the in-memory morph resamples with (:func:`.interpolate.resample_box`), so
the values are the in-memory ones bit for bit. Attributes likewise (their
border samples beyond their grid). The alignment's centre (a shape's
centroid) is summed by blocks in integers (:func:`block_matrices`).

Refused (:func:`block_grid` and :func:`check_covered` say why): a landmark
warp; a frame grid reaching beyond an aligned input's grid (those voxels are
filled in memory by the shift-and-increment propagation across the whole
field, :func:`volwarp_cli.distance.update.fill_uncovered`, which has no
by-blocks form); an input box too big for one task's memory (a strong
scaling, when even the smallest blocks would need it).
:func:`volwarp_cli.morph.run.morph_by_blocks` runs these steps in order.
"""

from __future__ import annotations

import functools

import numpy as np

from ..box import Box
from ..errors import VolwarpError
from ..geometry import Geometry
from .fields import INPUT_BYTES_PER_VOXEL, RESAMPLE_BYTES_PER_VOXEL
from .frames import FRAME_BYTES_PER_VOXEL
from .grid import choose_grid
from .interpolate import (
    index_map,
    lands_on_grid,
    needed_box,
    resample_box,
)
from .spec import MorphJob

#: Bytes per voxel a mesh block holds: the frame field (12 with both inputs) and the
#: flying edges' arrays
MESH_BYTES_PER_VOXEL = 36


def block_grid(job: MorphJob, source: Geometry, target: Geometry,
               attributes: dict[str, tuple[Geometry, Geometry]] | None = None,
               source_matrix: np.ndarray | None = None, target_matrix: np.ndarray | None = None
               ) -> tuple[Geometry, str | None]:
    """``(frame grid, why the morph cannot run by blocks or None)``.

    The grid by the in-memory rules (:func:`.grid.choose_grid` with the
    alignment matrices, :func:`block_matrices`: its GridError is the
    in-memory one). Inputs on other grids, moved or not, are resampled by
    blocks; a landmark warp is not run by blocks. ``attributes`` is kept for
    the callers (every attribute is resampled as its shape is).
    """
    eye = np.eye(4)
    a_s = eye if source_matrix is None else source_matrix
    a_t = eye if target_matrix is None else target_matrix
    grid = choose_grid(job.grid, source, target, a_s, a_t, moved=job.moved, margin=job.margin)
    if job.warp_source_points is not None:
        return grid, ("its landmark warp's thin-plate/Gaussian map is evaluated through "
                      "matrix products whose rounding is not guaranteed to be the same block "
                      "by block")
    return grid, None


def resample_chunks(shape, chunks, maps, block_bytes: int) -> tuple[int, int, int]:
    """Blocks of the frame grid whose resampling fits ``block_bytes``: ``chunks`` or halves.

    ``maps``: ``(index map, input shape)`` of every input resampled. A block
    holds its coordinates and output (:data:`RESAMPLE_BYTES_PER_VOXEL`) and
    the input box it reads (:data:`INPUT_BYTES_PER_VOXEL`,
    :func:`.interpolate.needed_box`); where some block's does not fit, the
    blocks' longest side is halved, until single voxels. A VolwarpError when
    even those do not fit (a strong scaling: one frame voxel reaching a huge
    input box).
    """
    c = [max(1, min(int(a), int(n))) for a, n in zip(chunks, shape, strict=True)]
    whole = Box.from_shape(shape)
    while True:
        worst = 0
        for box in whole.blocks(tuple(c)):
            for m, values_shape in maps:
                need = needed_box(m, box, values_shape).size * INPUT_BYTES_PER_VOXEL
                worst = max(worst, need + box.size * RESAMPLE_BYTES_PER_VOXEL)
            if worst > block_bytes:
                break
        if worst <= block_bytes:
            return tuple(c)
        if max(c) == 1:
            raise VolwarpError(
                f"resampling an input onto the frame grid needs {worst / 2**20:.1f} MiB for a "
                f"single voxel (the alignment scales it strongly), more than a block's "
                f"{block_bytes / 2**20:.1f} MiB: raise --memory-limit or run in memory")
        axis = int(np.argmax(c))
        c[axis] = (c[axis] + 1) // 2


def _uncovered_task(box: Box, *, m, values_shape):
    need = needed_box(m, box, values_shape)
    ones = np.ones(need.shape, np.float32)  # finite samples: NaN exactly where uncovered
    return int(np.isnan(resample_box(ones, need, m, box, values_shape=values_shape,
                                          outside="nan")).sum())


def check_covered(job: MorphJob, geometries: dict, matrices: dict, grid: Geometry, run,
                  chunks) -> str | None:
    """``(why, advice)`` where the fields cannot be resampled by blocks (a frame voxel they do not cover), else None.

    ``geometries``, ``matrices``: ``{"source": ..., "target": ...}``. A frame
    voxel outside a moved input's grid gets its field from the in-memory
    fill (a propagation across the whole field); counted block by block,
    with the in-memory resampling's NaN rule, before any field is computed.
    """
    for name in ("source", "target"):
        geo, mat = geometries[name], matrices[name]
        if lands_on_grid(geo.shape, geo.index_to_world_matrix, mat, grid):
            continue
        m = index_map(geo.index_to_world_matrix, mat, grid)
        task = functools.partial(_uncovered_task, m=m, values_shape=tuple(geo.shape))
        count = sum(run(task, Box.from_shape(grid.shape).blocks(chunks)))
        if count:
            return (f"its frame grid reaches beyond the {name}'s grid through its alignment "
                    f"or grid ({count} of {grid.size} frame voxels uncovered), and the "
                    "in-memory morph fills such voxels by a propagation across the whole "
                    "field, which has no form by blocks",
                    "choose a grid the aligned inputs cover, e.g. grid: source with a target "
                    "that covers it, or an explicit grid")
    return None


def in_morph_terms(job: MorphJob, exc: VolwarpError) -> str:
    """The distance's refusal as a morph's: the morph's settings, not ``volwarp distance``'s."""
    from ..distance.band import SUBVOXEL_NEEDS_BAND

    if str(exc) != SUBVOXEL_NEEDS_BAND:
        return str(exc)
    if job.doc is not None:  # a spec
        how = ("set max_distance: D in the spec (each field clamped to [-D, D]), or surface: "
               "voxel for the exact field between voxel centres")
    else:
        how = ("give --max-distance D (each field clamped to [-D, D]), or use a spec with "
               "surface: voxel for the exact field between voxel centres")
    return f"smooth samples (a sub-voxel surface) morph by blocks only within a band: {how}"


def frame_chunks(shape, block_bytes: int, workers: int, block=None):
    """The frames' output blocks: ``block``, else whole rows within ``block_bytes``."""
    from ..passes import pass_boxes

    if block is not None:
        return tuple(block)
    return pass_boxes(shape, (2,), block_bytes=block_bytes,
                      bytes_per_voxel=FRAME_BYTES_PER_VOXEL, min_blocks=workers)[0].shape


def mesh_block_shape(shape, block_bytes: int, block=None) -> tuple[int, int, int]:
    """The frames' mesh blocks: ``block``, else slabs of whole planes within ``block_bytes``."""
    if block is not None:
        return tuple(block)
    nz, ny, nx = shape
    depth = block_bytes // max(1, MESH_BYTES_PER_VOXEL * ny * nx)
    return max(8, min(nz, depth, 256)), ny, nx
