"""Measure the vessel before and after straightening: how straight, how thick.

    python check.py --iso LEVEL BEFORE.nrrd AFTER.nrrd > check.txt

Both volumes are read as they are; nothing here knows the model. The vessel
runs along the volume's z axis. In every z slice the cross-section is the
connected region above LEVEL nearest the previous slice's centre (tracked up
from the largest region of the bottom slice); its intensity-weighted centroid
is a point of the centreline, and its area, times the cosine of the vessel's
slope there, is the cross-section's true area, so sqrt(area / pi) is the
lumen's radius even where the vessel runs at an angle. Slices where the
region is much larger than usual (the side branch joins there), and those
within two radii of them, are left out.

Straightness: the distance of each centreline point from the straight line
through the centroids of the bottom and top quarters of the slices. Thickness:
the median radius over the slices. Exits 1 (and says FAIL) unless, after the
warp, the largest deviation is below RATIO of the kink's (and below MAX_DEV
voxels) and the median radius is within RADIUS_TOL of the original's.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from scipy.ndimage import label

from volwarp_cli.io import read_volume

RATIO = 0.25       # straightened deviation / kinked deviation, at most
MAX_DEV = 1.5      # voxels
RADIUS_TOL = 0.15  # relative change of the median radius
BRANCH = 1.4       # a slice whose region is this many times the median area is a junction


def trace(path, iso):
    """Per z slice: centroid (world x y z), area (voxels), or NaN where not measured."""
    vol = read_volume(path)
    data = vol.data.astype(np.float64)
    nz = data.shape[0]
    cent = np.full((nz, 3), np.nan)
    area = np.full(nz, np.nan)
    prev = None
    for k in range(nz):
        sl = data[k]
        labels, n = label(sl >= iso)
        if n == 0:
            continue
        sums = np.bincount(labels.ravel(), minlength=n + 1)[1:]
        yy, xx = np.nonzero(labels)
        lab = labels[yy, xx]
        cy = np.bincount(lab, yy, n + 1)[1:] / sums
        cx = np.bincount(lab, xx, n + 1)[1:] / sums
        if prev is None:
            pick = int(np.argmax(sums)) + 1
        else:
            pick = int(np.argmin(np.hypot(cx - prev[0], cy - prev[1]))) + 1
        inside = labels == pick
        w = sl[inside]
        jy, jx = np.nonzero(inside)
        c = (float((w * jx).sum() / w.sum()), float((w * jy).sum() / w.sum()))
        prev = c
        cent[k] = vol.index_to_world([c[0], c[1], k])
        area[k] = inside.sum() * float(np.prod(vol.spacing[:2]))
    usual = np.nanmedian(area)
    junction = area > BRANCH * usual
    # and the slices next to it, where the branch's root still pulls the centroid
    reach = int(np.ceil(2.0 * np.sqrt(usual / np.pi) / vol.spacing[2]))
    junction = np.convolve(junction, np.ones(2 * reach + 1), mode="same") > 0
    cent[junction] = np.nan
    area[junction] = np.nan
    return cent, area, int(junction.sum()), vol


def deviation(cent):
    ok = np.flatnonzero(~np.isnan(cent[:, 0]))
    q = max(len(ok) // 4, 2)
    a, b = cent[ok[:q]].mean(axis=0), cent[ok[-q:]].mean(axis=0)
    d = (b - a) / np.linalg.norm(b - a)
    rel = cent - a
    off = rel - (rel @ d)[:, None] * d[None]
    return np.linalg.norm(off, axis=1)


def radius(cent, area):
    """Radius of the true (perpendicular) cross-section, per slice."""
    step = np.gradient(cent, axis=0)  # world units per slice
    cos = np.abs(step[:, 2]) / np.linalg.norm(step, axis=1)
    return np.sqrt(area * cos / np.pi)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--iso", type=float, required=True)
    args = ap.parse_args()

    rows = {}
    for name, path in (("kinked", args.before), ("straightened", args.after)):
        cent, area, skipped, vol = trace(path, args.iso)
        dev = deviation(cent)
        rad = radius(cent, area)
        above = float((vol.data >= args.iso).sum() * np.prod(vol.spacing))
        rows[name] = dict(dev=dev, rad=rad, skipped=skipped, above=above,
                          measured=int(np.sum(~np.isnan(dev))), slices=len(dev))
    k, s = rows["kinked"], rows["straightened"]
    kink = np.nanmax(k["dev"])
    worst = np.nanmax(s["dev"])
    r0, r1 = np.nanmedian(k["rad"]), np.nanmedian(s["rad"])
    print(f"iso level {args.iso:g}; deviation = distance of the slice centroid from the straight "
          "line through the ends")
    print(f"{'':14s}{'slices':>8s}{'junction':>10s}{'max dev':>10s}{'mean dev':>10s}"
          f"{'radius':>8s}{'r min':>7s}{'r max':>7s}{'above iso':>11s}")
    for name, r in rows.items():
        print(f"{name:14s}{r['measured']:8d}{r['skipped']:10d}{np.nanmax(r['dev']):10.2f}"
              f"{np.nanmean(r['dev']):10.2f}{np.nanmedian(r['rad']):8.2f}{np.nanmin(r['rad']):7.2f}"
              f"{np.nanmax(r['rad']):7.2f}{r['above']:11.0f}")
    checks = [
        (f"straightened max deviation {worst:.2f} < {RATIO:g} x kinked {kink:.2f} "
         f"(= {RATIO * kink:.2f})", worst < RATIO * kink),
        (f"straightened max deviation {worst:.2f} < {MAX_DEV:g} voxel", worst < MAX_DEV),
        (f"median radius {r1:.2f} within {RADIUS_TOL:.0%} of {r0:.2f} "
         f"({r1 / r0 - 1:+.1%})", abs(r1 / r0 - 1) <= RADIUS_TOL),
    ]
    failed = 0
    for text, ok in checks:
        print(("ok    " if ok else "FAIL  ") + text)
        failed += not ok
    print(f"straightening: max deviation {kink:.2f} -> {worst:.2f} voxel "
          f"({worst / kink:.1%} of the kink)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
