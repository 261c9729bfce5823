"""Write the tree of True & Hughes 1992, Fig. 7: a sculpted tree on a mound, as two volumes.

    python make_tree.py TREE.nrrd LEAF.nrrd [--spacing MM]

The tree stands in a 100 x 100 x 128 mm box (z up): a mound, a trunk with a root
flare, six branches (tubes along curves) and a crown of blobs. Every part is a
signed distance (mm, negative inside), the parts are joined by smooth minima,
and the density is a 2-voxel ramp across the surface, lightly blurred: a smooth
field whose level 127 is a smooth surface. Nothing touches the box's sides or top;
the mound's flat underside is 3 mm above the bottom.

TREE.nrrd is the density (uint8, 0 outside, 255 inside, surface at 127).
LEAF.nrrd labels the material (255 foliage, 0 wood, a smooth step between), for
the figure's colours; it is warped with the same spec as the tree.

--spacing 1 (the default) gives 100 x 100 x 128 voxels, --spacing 2 gives 50 x 50 x 64
(SIZE=small); the world box, and so every world coordinate, is the same.
The crown's blobs come from a fixed seed: the same command writes the same bytes.
"""

import argparse

import numpy as np
from scipy.ndimage import gaussian_filter

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

BOX = np.array([100.0, 100.0, 128.0])  # world box (x, y, z) in mm, from the origin
AXIS = (50.0, 50.0)                    # where the trunk stands
GROUND = 3.0                           # the mound's flat underside
SEED = 1992
FAR = 1e3                              # "no surface near": the start of every union


def smin(a, b, k):
    """Polynomial smooth minimum (a smooth union of two distance fields), blend width k mm."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def smax(a, b, k):
    return -smin(-a, -b, k)


class Field:
    """A distance field on the voxel centres, built up by smooth unions of parts.

    Each part is evaluated only inside its bounding box (plus a margin): further
    out it is too far to change the union, and the tree is built in about a second.
    """

    def __init__(self, spacing):
        self.sp = spacing
        self.shape = np.rint(BOX / spacing).astype(int)  # (x, y, z)
        # voxel centres at sp/2, 3 sp/2, ...: the voxel boxes tile [0, BOX]
        self.axes = [spacing * (np.arange(n) + 0.5) for n in self.shape]
        self.d = np.full(self.shape[::-1], FAR)

    def union(self, part, lo, hi, k):
        """d = smin(d, part(p), k) where the part (inside box lo..hi) can matter."""
        margin = k + 3.0 * self.sp
        sl = []
        for ax, a, b in zip(self.axes, lo, hi, strict=True):
            i0 = int(np.searchsorted(ax, a - margin))
            i1 = int(np.searchsorted(ax, b + margin))
            sl.append(slice(i0, i1))
        z, y, x = np.meshgrid(self.axes[2][sl[2]], self.axes[1][sl[1]], self.axes[0][sl[0]],
                              indexing="ij")
        sub = (sl[2], sl[1], sl[0])
        self.d[sub] = smin(self.d[sub], part(x, y, z), k)


def capsule(a, b, ra, rb):
    """A tube from a to b whose radius goes from ra to rb."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a

    def part(x, y, z):
        px, py, pz = x - a[0], y - a[1], z - a[2]
        t = np.clip((px * ab[0] + py * ab[1] + pz * ab[2]) / (ab @ ab), 0.0, 1.0)
        dist = np.sqrt((px - t * ab[0]) ** 2 + (py - t * ab[1]) ** 2 + (pz - t * ab[2]) ** 2)
        return dist - (ra + (rb - ra) * t)

    r = max(ra, rb)
    return part, np.minimum(a, b) - r, np.maximum(a, b) + r


def ellipsoid(c, r):
    c, r = np.asarray(c, float), np.asarray(r, float)

    def part(x, y, z):
        s = np.sqrt(((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((z - c[2]) / r[2]) ** 2)
        return (s - 1.0) * r.min()

    return part, c - r, c + r


def trunk(x, y, z):
    """A gently wavy axis, radius 5 -> 2.5 mm with a root flare, from the ground to z = 100."""
    cx = AXIS[0] + 1.5 * np.sin(z / 23.0)
    cy = AXIS[1] + 1.0 * np.sin(z / 31.0 + 1.0)
    up = np.clip(z - 8.0, 0.0, None)
    r = 5.0 - 2.5 * np.clip(up / 92.0, 0.0, 1.0) + 4.0 * np.exp(-up / 5.0)
    return smax(np.hypot(x - cx, y - cy) - r, z - 100.0, 1.0)


def bezier(p0, p1, p2, n):
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t ** 2 * p2


def plan_tree():
    """Branches (polylines with radii) and crown blobs (centre, radii), world mm, fixed seed."""
    rng = np.random.default_rng(SEED)
    branches, crown = [], []
    # the main crown: one broad ellipsoid over the trunk's top
    top = np.array([AXIS[0] + 1.0, AXIS[1], 96.0])
    crown.append((top, np.array([21.0, 21.0, 17.0])))
    # six branches leaving the trunk between z = 44 and 78, each ending in a clump
    for i in range(6):
        az = np.radians(20.0 + 137.5 * i + rng.uniform(-12, 12))
        dirn = np.array([np.cos(az), np.sin(az), 0.0])
        z0 = 44.0 + 6.8 * i
        reach = rng.uniform(19.0, 24.0) - 0.5 * i
        lift = rng.uniform(16.0, 22.0)
        start = np.array([AXIS[0], AXIS[1], z0])
        mid = start + dirn * reach * 0.55 + np.array([0, 0, lift * 0.2])
        end = start + dirn * reach + np.array([0, 0, lift])
        branches.append((bezier(start, mid, end, 6), np.linspace(2.8, 2.0, 6)))
        rad = rng.uniform(11.0, 13.5)
        crown.append((end + np.array([0, 0, 3.0]), np.array([rad, rad, rad * 0.8])))
    # lumps: small blobs scattered over the main crown's upper surface
    for _ in range(10):
        az = rng.uniform(0, 2 * np.pi)
        el = rng.uniform(0.1, 1.2)
        rad = rng.uniform(7.0, 10.0)
        off = np.array([np.cos(az) * np.cos(el) * 19.0, np.sin(az) * np.cos(el) * 19.0,
                        np.sin(el) * 14.0])
        crown.append((top + off, np.array([rad, rad, rad])))
    return branches, crown


def build(spacing):
    """(wood, foliage) distance fields (mm) on the voxel centres, [z, y, x]."""
    branches, crown = plan_tree()
    wood = Field(spacing)
    # a mound, flattened below, with the trunk rising out of it
    wood.union(*ellipsoid((AXIS[0], AXIS[1], 2.0), (30.0, 30.0, 9.0)), k=1.0)
    wood.union(trunk, (AXIS[0] - 10, AXIS[1] - 10, 0.0), (AXIS[0] + 10, AXIS[1] + 10, 101.0), k=4.0)
    for pts, radii in branches:
        for i in range(len(pts) - 1):
            wood.union(*capsule(pts[i], pts[i + 1], radii[i], radii[i + 1]), k=1.5)
    z = wood.axes[2][:, None, None]
    wood.d = smax(wood.d, GROUND - z, 1.0)
    leaves = Field(spacing)
    for c, r in crown:
        leaves.union(*ellipsoid(c, r), k=5.0)
    return wood, leaves


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tree")
    ap.add_argument("leaf")
    ap.add_argument("--spacing", type=float, default=1.0, help="voxel size in mm (1 or 2)")
    args = ap.parse_args()
    sp = args.spacing
    wood, leaves = build(sp)
    d = smin(wood.d, leaves.d, 2.0)
    ramp = 2.0 * sp  # density 255 -> 0 across two voxels
    dens = gaussian_filter(np.clip(0.5 - d / ramp, 0.0, 1.0) * 255.0, 0.6)
    leaf = 255.0 / (1.0 + np.exp(np.clip((leaves.d - wood.d) / sp, -40, 40)))
    for data, path in ((dens, args.tree), (leaf, args.leaf)):
        vol = Volume(np.rint(data).astype(np.uint8), spacing=(sp, sp, sp),
                     origin=(sp / 2, sp / 2, sp / 2), space="3d-right-handed")
        write_volume(vol, path)


if __name__ == "__main__":
    main()
