"""Check the warp numerically: the spout went down by the spec's amount, the body stayed put.

    python check.py SPEC.yaml TEAPOT.nrrd LOWERED.nrrd > check.txt

Both volumes must share one grid (`volwarp warp --crop`). World mm, z up.

- The *spout* is the material beyond x = SPOUT_X, its *tip* the material
  beyond x = TIP_X. The spout's highest surface point (the 127 level,
  interpolated along z) must go down by the spec's tip drag (the drag whose
  `from` is highest) within TOL of it; the tip's centroid (density-weighted)
  must go down at least MIN_TIP of it (a bend moves the whole tip, a bump
  only its top); the whole spout's centroid at least 0.3 of it.
- The *body* far from the spout, x < BODY_X, lies outside the support of
  every control point the drags may move: there the warp is the identity,
  and the volume may differ only by resampling (capture and pushforward).
  At most MAX_FLIP of its inside voxels (density >= 127) may change side, and
  its enclosed volume may change by at most MAX_FLIP.

Prints what it measured; exits 1 when a check fails.
"""

from __future__ import annotations

import sys

import numpy as np
import yaml

from volwarp_cli.io import read_volume

ISO = 127.0
SPOUT_X = 72.0  # mm: the material beyond this is the spout (the body ends at 67)
TIP_X = 84.0  # mm: the spout beyond this is its tip
BODY_X = 55.0  # mm: the body, lid, knob and handle before this are "far from the spout"
TOL = 0.15  # the spout's top point goes down by the tip drag, within 15% of it
MIN_TIP = 0.7  # the tip's centroid goes down at least 70% of the tip drag (a bend, not a bump)
MAX_FLIP = 0.005  # body: at most 0.5% of its inside voxels change side


def world_axes(vol):
    """World x, y, z of the voxel centres along each axis (axis-aligned grids only)."""
    if not np.allclose(vol.direction, np.eye(3)):
        sys.exit("check.py: expects an axis-aligned volume")
    return [vol.origin[a] + vol.spacing[a] * np.arange(n) for a, n in enumerate(vol.shape_xyz)]


def top_surface(data, z):
    """Highest z (interpolated) where a column of data[z, y, x] crosses ISO downwards."""
    above = data >= ISO
    cross = above[:-1] & ~above[1:]  # slice k inside, slice k + 1 outside
    ks = np.nonzero(cross.any(axis=(1, 2)))[0]
    if len(ks) == 0:
        sys.exit("check.py: no material in the spout tip region")
    k = int(ks[-1])  # the highest slice with a crossing holds the highest point
    a = data[k][cross[k]].astype(np.float64)
    b = data[k + 1][cross[k]].astype(np.float64)
    return float(np.max(z[k] + (a - ISO) / (a - b) * (z[k + 1] - z[k])))


def centroid_z(vol, x_min):
    """Density-weighted mean z of the material beyond x = x_min."""
    x, _, z = world_axes(vol)
    w = vol.data[:, :, x > x_min].astype(np.float64).sum(axis=(1, 2))
    return float((w * z).sum() / w.sum())


def top_z(vol, x_min=-np.inf):
    """Highest surface point (z) of the material beyond x = x_min."""
    x, _, z = world_axes(vol)
    return top_surface(vol.data[:, :, x > x_min], z)


def main(argv):
    spec_path, before_path, after_path = argv
    with open(spec_path) as fh:
        spec = yaml.safe_load(fh)
    if spec.get("units", "world") != "world":
        sys.exit("check.py: the spec's handles must be in world units")
    drags = [d for st in spec["steps"] for d in st.get("drag", [])]
    tip = max(drags, key=lambda d: d["from"][2])
    want = float(tip["from"][2] - tip["to"][2])

    before, after = read_volume(before_path), read_volume(after_path)
    if before.data.shape != after.data.shape or not np.allclose(before.origin, after.origin):
        sys.exit("check.py: the volumes have different grids (warp with --crop)")

    failures = []

    def report(what, z0, z1, lo, hi):
        drop = z0 - z1
        ok = lo * want <= drop <= hi * want
        if not ok:
            failures.append(f"{what} went down {drop:.2f} mm, not {lo * want:.2f}-{hi * want:.2f}")
        print(f"{what:34s} z {z0:6.2f} -> {z1:6.2f} mm   down {drop:6.2f} mm "
              f"({100 * drop / want:5.1f}% of the drag)   {'ok' if ok else 'FAIL'}")
        return drop

    print(f"# tip drag of the spec: {want:.2f} mm down (world mm, z up)")
    drop = report(f"spout top point (x > {SPOUT_X:g} mm)", top_z(before, SPOUT_X),
                  top_z(after, SPOUT_X), 1 - TOL, 1 + TOL)
    report(f"spout tip centroid (x > {TIP_X:g} mm)", centroid_z(before, TIP_X),
           centroid_z(after, TIP_X), MIN_TIP, 1 + TOL)
    report(f"whole spout centroid (x > {SPOUT_X:g} mm)", centroid_z(before, SPOUT_X),
           centroid_z(after, SPOUT_X), 0.3, 1 + TOL)
    z = world_axes(before)[2]
    foot = float(z[np.nonzero(np.any(before.data >= ISO, axis=(1, 2)))[0][0]])
    height = top_z(before) - foot  # knob top to foot (the foot: its lowest voxel centre)
    print(f"teapot height (foot to knob) {height:.2f} mm: the spout's top went down "
          f"{100 * drop / height:.1f}% of it")

    x, _, _ = world_axes(before)
    body = x < BODY_X
    a, b = before.data[:, :, body] >= ISO, after.data[:, :, body] >= ISO
    inside = int(a.sum())
    flips = int((a != b).sum())
    change = abs(int(b.sum()) - inside) / inside
    mean_diff = float(np.mean(np.abs(before.data[:, :, body].astype(np.float64)
                                     - after.data[:, :, body].astype(np.float64))))
    ok = flips <= MAX_FLIP * inside and change <= MAX_FLIP
    failures += [] if ok else [f"body (x < {BODY_X:g} mm) changed: {flips} voxels flipped"]
    print(f"# body, lid and handle (x < {BODY_X:g} mm): {inside} inside voxels")
    print(f"body voxels changing side {flips} ({100 * flips / inside:.3f}%), inside volume "
          f"change {100 * change:.3f}%, mean |density change| {mean_diff:.3f} of 255   "
          f"{'ok' if ok else 'FAIL'}")
    for f in failures:
        print(f"check.py: {f}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
