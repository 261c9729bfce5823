"""Sculpt the teapot of True & Hughes 1992, Figure 6, from implicit primitives.

    python make_teapot.py teapot.nrrd [--size N]

The teapot lives in a 96 x 96 x 96 mm box (world x y z in mm, z up, the box
[0, 96]^3 whatever the voxel count): N^3 uint8 voxels of 96/N mm, density 255
inside and 0 outside with a linear ramp RAMP voxels wide across the surface
(so the 127 isosurface is smooth). Primitives, each an (approximate) signed
distance in mm, joined by their minimum:

- body: an ellipsoid (semi-axes 23, 23, 18 mm, centre (44, 48, 36)) cut flat
  at z = 21 (its foot);
- lid: a flat ellipsoid (13, 13, 5) resting on the body's top, and a knob,
  a 4 mm sphere on a short neck;
- handle: a torus segment in the x-z plane on the -x side (radius 11 mm,
  tube 2.8 mm), its inner part hidden in the body;
- spout: a tube along a quadratic Bezier curve from inside the body, out on
  the +x side and up to a tip at (87, 48, 53), tapering from 7 to 3.5 mm.

The teapot stays at least 5 mm from every face of the box. The same command
gives the same bytes.
"""

from __future__ import annotations

import argparse

import numpy as np

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

BOX = 96.0  # mm
RAMP = 2.5  # width of the density ramp across the surface, voxels

# the spout's curve (world mm): from inside the body, out, and up to the tip
SPOUT = np.array([[62.0, 48.0, 28.0], [77.0, 48.0, 31.0], [87.0, 48.0, 53.0]])
SPOUT_RADIUS = (7.0, 3.5)  # at the base, at the tip


def ellipsoid(x, y, z, centre, radii):
    """Approximate signed distance to an ellipsoid (exact on the axes)."""
    px, py, pz = ((c - c0) for c, c0 in zip((x, y, z), centre, strict=True))
    rx, ry, rz = radii
    k0 = np.sqrt((px / rx) ** 2 + (py / ry) ** 2 + (pz / rz) ** 2)
    k1 = np.sqrt((px / rx**2) ** 2 + (py / ry**2) ** 2 + (pz / rz**2) ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def sphere(x, y, z, centre, r):
    return np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) - r


def torus_xz(x, y, z, centre, big, small):
    """A torus whose axis is the y axis through ``centre`` (it lies in the x-z plane)."""
    q = np.sqrt((x - centre[0]) ** 2 + (z - centre[2]) ** 2) - big
    return np.sqrt(q**2 + (y - centre[1]) ** 2) - small


def cylinder_z(x, y, z, centre, r, z0, z1):
    """A vertical cylinder of radius r between heights z0 and z1."""
    d_side = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2) - r
    d_caps = np.maximum(z0 - z, z - z1)
    outside = np.sqrt(np.maximum(d_side, 0) ** 2 + np.maximum(d_caps, 0) ** 2)
    return outside + np.minimum(np.maximum(d_side, d_caps), 0)


def tube(x, y, z, curve, radii, segments=48):
    """A round tube along a quadratic Bezier curve, its radius tapering linearly."""
    t = np.linspace(0.0, 1.0, segments + 1)
    p0, p1, p2 = curve
    pts = ((1 - t) ** 2)[:, None] * p0 + (2 * (1 - t) * t)[:, None] * p1 + (t**2)[:, None] * p2
    rad = radii[0] + (radii[1] - radii[0]) * t
    best = np.full(x.shape, np.inf)
    p = np.stack([x, y, z], axis=-1)
    for a, b, ra, rb in zip(pts[:-1], pts[1:], rad[:-1], rad[1:], strict=True):
        ab = b - a
        h = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
        d = np.linalg.norm(p - a - h[..., None] * ab, axis=-1) - (ra + h * (rb - ra))
        np.minimum(best, d, out=best)
    return best


def teapot_distance(x, y, z):
    """Signed distance (mm, negative inside) of the whole teapot."""
    body = np.maximum(ellipsoid(x, y, z, (44.0, 48.0, 36.0), (23.0, 23.0, 18.0)), 21.0 - z)
    lid = ellipsoid(x, y, z, (44.0, 48.0, 52.5), (13.0, 13.0, 5.0))
    neck = cylinder_z(x, y, z, (44.0, 48.0), 2.0, 55.0, 60.0)
    knob = sphere(x, y, z, (44.0, 48.0, 61.0), 4.0)
    handle = torus_xz(x, y, z, (20.0, 48.0, 38.0), 11.0, 2.8)
    spout = tube(x, y, z, SPOUT, SPOUT_RADIUS)
    return np.minimum.reduce([body, lid, neck, knob, handle, spout])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("output")
    ap.add_argument("--size", type=int, default=96, help="voxels per axis (default 96)")
    args = ap.parse_args(argv)
    n = args.size
    h = BOX / n
    c = (np.arange(n) + 0.5) * h  # voxel centres, mm
    data = np.empty((n, n, n), np.uint8)
    for k in range(n):  # one z slice at a time keeps memory small
        y, x = np.meshgrid(c, c, indexing="ij")
        d = teapot_distance(x, y, np.full_like(x, c[k]))
        # density 255 inside, 0 outside, a linear ramp RAMP voxels wide across the surface
        data[k] = np.rint(255.0 * np.clip(0.5 - d / (RAMP * h), 0.0, 1.0)).astype(np.uint8)
    write_volume(Volume(data, spacing=(h, h, h), origin=(h / 2, h / 2, h / 2),
                        space="left-posterior-superior"), args.output)


if __name__ == "__main__":
    main()
