"""Write the warp spec that straightens the kink: drag handles along the vessel.

    python make_spec.py OUT.yaml [--size full|small] [--lattice NX NY NZ] [--oversample G]
                                 [--pushforward nearest|box]

About every STEP voxels of arc length along the centreline, from the bottom
of the volume to its top, nine handles: the centreline point and eight points
on a ring of RING x the lumen radius around it. Each goes from where
it is in the kinked vessel to where the unbending map of vessel.py sends it
on the straight line. All handles are solved together (least norm, paper
section 7), so the warp moves the whole cross-section, not just the axis.
Handles on the straight parts keep their place (bottom) or move up by the
length the kink took (top). Coordinates are input voxels (units: voxel).
"""

from __future__ import annotations

import argparse

import numpy as np
from vessel import Centreline, geometry

# Handle spacing along the vessel (full-size voxels): just under the lattice's z
# spacing (128 / 26 = 4.9). Handles denser than the control points make the
# least-norm system ill-conditioned (control points moved by 1e4..1e10 voxels).
STEP = 4.6
# Ring radius / lumen radius: the ring holds the lumen and its blurred edge. Inside
# the bend the unbending map stretches without bound (it is singular at the centre
# of curvature); just outside the ring the warp folds there, so keep that fold in
# the background (1.0 dents the lumen's inner wall, 1.5 makes it ragged).
RING = 1.25
SPOKES = 8  # handles on each ring


def fmt(p):
    return "[" + ", ".join(f"{v:.2f}" for v in p) + "]"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("output")
    ap.add_argument("--size", default="full", choices=["full", "small"])
    ap.add_argument("--lattice", type=int, nargs=3, default=(19, 13, 29))
    ap.add_argument("--oversample", type=float, default=2.0)
    ap.add_argument("--pushforward", default="box", choices=["nearest", "box"])
    args = ap.parse_args()

    g = geometry(args.size)
    line = Centreline(g)
    nz = g.shape[2]
    scale = nz / 128
    step = STEP * scale
    ring = RING * g.radius
    angles = np.linspace(0.0, 2.0 * np.pi, SPOKES, endpoint=False)
    offsets = [(0.0, 0.0)] + [(ring * np.cos(t), ring * np.sin(t)) for t in angles]
    # from the bottom to the top of the volume (the ends are straight: the rings are level)
    s_lo, s_hi = line.s_at_z(0.0), line.s_at_z(nz - 1.0)
    levels = np.linspace(s_lo, s_hi, int(np.ceil((s_hi - s_lo) / step)) + 1)

    lines = [
        "# Straighten the synthetic angiogram's kinked vessel (written by make_spec.py:",
        "# do not edit). Each handle takes a point of the kinked vessel (its axis, and",
        f"# {SPOKES} points on a ring of radius {ring:g} around it, every "
        f"{levels[1] - levels[0]:.2f} voxels",
        "# of arc length) to where it lies on the straightened vessel. Coordinates are",
        "# input voxel indices (x, y, z).",
        "version: 1",
        "units: voxel",
        f"capture: {{lattice: [{', '.join(str(n) for n in args.lattice)}], "
        f"oversample: {args.oversample:g}}}",
        f"pushforward: {args.pushforward}",
        "steps:",
        "  - name: straighten the kink",
        "    drag:",
    ]
    for s in levels:
        for a, b in offsets:
            src, dst = line.kinked(s, a, b), line.straight(s, a, b)
            lines.append(f"      - {{from: {fmt(src)}, to: {fmt(dst)}}}")
    with open(args.output, "w") as fh:
        fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
