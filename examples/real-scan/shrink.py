"""Halve a scan's resolution in x and y (index axes) for SIZE=small runs.

    python shrink.py IN.nrrd OUT.nrrd

Averages 2 x 2 blocks of voxels along the first two index axes (the 128 x 128
in-plane grid of the coronal scan; its 62 slices stay), so the result has a
quarter of the voxels at 4 x 4 x 3 mm. The geometry is kept exactly: the
spacing doubles and the origin moves to the centre of the first 2 x 2 block,
so the head stays where it was in world coordinates.
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np

from volwarp_cli.io import read_volume, write_volume

src, dst = sys.argv[1:]
vol = read_volume(src)
a = vol.data  # [z, y, x]
nz, ny, nx = a.shape
a = a[:, : ny // 2 * 2, : nx // 2 * 2].astype(np.float64)
small = a.reshape(nz, ny // 2, 2, nx // 2, 2).mean(axis=(2, 4))
small = np.rint(small).astype(vol.data.dtype)
spacing = np.array(vol.spacing, dtype=np.float64) * [2.0, 2.0, 1.0]
# first voxel centre of the new grid: halfway between old voxels (0,0,0) and (1,1,0)
origin = vol.index_to_world(np.array([0.5, 0.5, 0.0]))
out = replace(vol, data=small, spacing=spacing, origin=np.asarray(origin, np.float64).ravel(),
              meta=dict(vol.meta, shrink="2x2x1 block mean of " + src.rsplit("/", 1)[-1]))
write_volume(out, dst)
