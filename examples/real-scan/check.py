"""Check that the warp's handles landed where the spec says, in world coordinates (LPS mm).

    python check.py SPEC.yaml from:FILE:ISO:INSIDE to:FILE:ISO:INSIDE [to:...] > landmarks.txt

For every drag handle (from -> to) of the spec, walk along the handle's line
from outside the head inwards and find where the surface (level ISO of FILE;
INSIDE = above for the scan, below for a signed distance field) is first
crossed. On a `from:` volume (the original) that crossing should be the
handle's `from` point, on a `to:` volume (a warped one) its `to` point.
Prints one line per handle and volume; exits 1 when any crossing misses by
more than TOL mm (environment, default 2: the scan's voxels are 2 x 2 x 3 mm).
"""

from __future__ import annotations

import os
import sys

import numpy as np
import yaml
from scipy.ndimage import map_coordinates

from volwarp_cli.io import read_volume

TOL = float(os.environ.get("TOL", "2"))


def sample(vol, data, points, outside):
    idx = vol.world_to_index(points)  # (N, 3): x y z voxel indices
    return map_coordinates(data.astype(np.float64), idx[:, ::-1].T, order=1, mode="constant",
                           cval=outside)


def crossing(vol, target, outward, iso, inside, reach=60.0, step=0.05):
    """First point of the ray target + t * outward (t from +reach down to -reach) inside the shape."""
    data = vol.data
    outside = float(data.min() if inside == "above" else data.max())
    t = np.arange(reach, -reach, -step)
    pts = target[None] + t[:, None] * outward[None]
    vals = sample(vol, data, pts, outside)
    ins = vals >= iso if inside == "above" else vals < iso
    first = int(np.argmax(ins))
    if not ins[first]:
        return None
    if first == 0:
        return pts[0]
    a, b = vals[first - 1], vals[first]  # linear interpolation between the two samples
    f = (iso - a) / (b - a) if b != a else 0.0
    return pts[first - 1] + f * (pts[first] - pts[first - 1])


def centroid(vol, iso, inside):
    data = vol.data
    mask = data >= iso if inside == "above" else data < iso
    zyx = np.argwhere(mask).mean(axis=0)
    return vol.index_to_world(zyx[::-1])


def fmt(p):
    return "(" + ", ".join(f"{c:6.1f}" for c in p) + ")"


def main(argv):
    spec_path, *runs = argv
    with open(spec_path) as fh:
        spec = yaml.safe_load(fh)
    if spec.get("units", "world") != "world":
        sys.exit("check.py: the spec's handles must be in world units")
    handles = [(st.get("name", f"step {s}"), np.array(h["from"], float), np.array(h["to"], float))
               for s, st in enumerate(spec["steps"]) for h in st.get("drag", [])]
    worst = 0.0
    centre = None
    print(f"# skin points along each handle's line, world LPS mm (tolerance {TOL} mm)")
    for run in runs:
        which, path, iso, inside = run.split(":")
        vol = read_volume(path)
        if centre is None:
            centre = centroid(vol, float(iso), inside)  # of the first (original) volume
            print(f"# head centre (centroid of the shape in {os.path.basename(path)}): {fmt(centre)}")
        for name, src, dst in handles:
            line = (dst - src) / np.linalg.norm(dst - src)
            outward = line if np.dot(line, src - centre) > 0 else -line
            target = src if which == "from" else dst
            hit = crossing(vol, target, outward, float(iso), inside)
            miss = np.inf if hit is None else float(np.linalg.norm(hit - target))
            worst = max(worst, miss)
            print(f"{os.path.basename(path):26s} {name:26s} {which:4s} {fmt(target)}  "
                  f"surface at {'none' if hit is None else fmt(hit)}  miss {miss:4.1f} mm")
    if worst > TOL:
        print(f"check.py: a handle misses its surface point by {worst:.1f} mm > {TOL} mm",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
