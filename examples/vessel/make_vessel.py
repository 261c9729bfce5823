"""Write the synthetic angiogram: a kinked, bright vessel with a side branch (uint8, 1 mm voxels).

    python make_vessel.py OUT.nrrd [--size full|small]

The lumen is bright (235 on the axis, 190 at the wall, background included: a
parabolic flow profile), its edge blurred over about a voxel, so the level 105
lies at the lumen's radius. The background is dim, smooth, seeded noise (about 5-35), the
kind of texture an MR angiogram has outside the vessels. Deterministic: the
same command writes the same bytes.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree
from scipy.special import erfc
from vessel import Centreline, branch_segment, geometry

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

CENTRE, WALL = 215.0, 170.0  # lumen density on the axis and at the wall
EDGE = 0.6                   # blur of the lumen's edge (voxels, Gaussian sigma)
BACKGROUND = 20.0            # mean density outside the vessels


def lumen(d, r):
    """Density at distance d from the axis of a vessel of radius r."""
    profile = WALL + (CENTRE - WALL) * (1.0 - np.minimum(d / r, 1.0) ** 2)
    return profile * 0.5 * erfc((d - r) / (EDGE * np.sqrt(2.0)))


def segment_distance(points, a, b):
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("output")
    ap.add_argument("--size", default="full", choices=["full", "small"])
    args = ap.parse_args()

    g = geometry(args.size)
    nx, ny, nz = g.shape
    line = Centreline(g)
    zz, yy, xx = np.mgrid[0:nz, 0:ny, 0:nx].astype(np.float64)
    voxels = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)

    d_main, _ = cKDTree(line.points).query(voxels, distance_upper_bound=4 * g.radius)
    d_main = np.minimum(d_main, 4 * g.radius)  # inf (nothing near) -> far enough
    d_branch = segment_distance(voxels, *branch_segment(g))
    vessel = np.maximum(lumen(d_main, g.radius), lumen(d_branch, g.branch_radius))

    rng = np.random.default_rng(1992)
    noise = gaussian_filter(rng.standard_normal((nz, ny, nx)), 1.5 * nx / 80)
    noise *= 6.0 / noise.std()
    data = vessel.reshape(nz, ny, nx) + BACKGROUND + noise
    write_volume(Volume(np.rint(np.clip(data, 0, 255)).astype(np.uint8),
                        space="left-posterior-superior"), args.output)


if __name__ == "__main__":
    main()
