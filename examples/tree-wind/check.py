"""Check the bend: per height, how far the tree moved downwind, against the spec.

    python check.py SPEC.yaml UPRIGHT.nrrd BENT.nrrd:F [BENT.nrrd:F ...] > check.txt

BENT.nrrd:F is a warped tree and the fraction F of the spec's moves it shows
(a frame of the gust step: 0.5 half way, 1 all of it).

Every lattice layer of the spec moves by one vector (u_k, 0, w_k) (the script
checks that), so the warp carries each horizontal slice of the tree, whole, to
height z + w(z) and u(z) downwind, with u and w the uniform cubic B-splines of
the layers' moves (paper eq. 1), evaluated here from the spec alone. The
measure is the density-weighted centroid of each z slice (world mm): the
centroid of the bent tree's slice at z + F w(z), less the upright tree's at z,
is its move. Per slice it must match F u(z) within TOL mm; per height band
(10 mm) the table prints the measured move, the spline's and the intended
profile's (make_spec.py: GUST * s^2), and the checks are that the base (below
16 mm) stays within 0.5 mm of where it was, that the move never shrinks going
up (by more than 0.3 mm from one band to the next), and that the top of the tree
moves F * GUST within 10 %. Exits 1 on any failure.

TOL (environment, default 1.0 mm) is about one voxel of the small build.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import yaml

from volwarp_cli.io import read_volume

sys.dont_write_bytecode = True  # importing make_spec leaves no __pycache__ here
from make_spec import ROOT, TOP, layer_move  # noqa: E402

TOL = float(os.environ.get("TOL", "1.0"))
BAND = 10.0      # mm
MIN_MASS = 0.02  # slices lighter than this fraction of the heaviest are not measured


def layer_moves(spec: dict, nz: int) -> np.ndarray:
    """(nz, 3) move of each lattice layer; every point of a layer must move alike."""
    moves: dict[int, set] = {}
    for step in spec["steps"]:
        if "drag" in step:
            sys.exit("check.py: the spec drags handles; it checks layer moves only")
        for mv in step.get("move", []):
            if "by" not in mv:
                sys.exit("check.py: the spec sets a point `to` a place; it checks `by` moves only")
            moves.setdefault(mv["index"][2], set()).add(tuple(mv["by"]))
    lat = spec["capture"]["lattice"]
    out = np.zeros((nz, 3))
    for k, vecs in moves.items():
        count = sum(1 for st in spec["steps"] for mv in st.get("move", []) if mv["index"][2] == k)
        if len(vecs) != 1 or count != lat[0] * lat[1]:
            sys.exit(f"check.py: layer {k} does not move as a whole ({count} points, "
                     f"{len(vecs)} different moves)")
        out[k] = vecs.pop()
    return out


def bspline(d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Uniform cubic B-spline of control values d (n, ...) at parameters s in [0, n - 3]."""
    a = np.clip(np.floor(s).astype(int), 0, len(d) - 4)
    t = (s - a)[:, None]
    b = np.concatenate([(1 - t) ** 3, 3 * t ** 3 - 6 * t ** 2 + 4, -3 * t ** 3 + 3 * t ** 2 + 3 * t + 1,
                        t ** 3], axis=1) / 6.0
    return sum(b[:, m:m + 1] * d[a + m] for m in range(4))


def slices(vol):
    """World z of each slice, its mass and its centroid's world x."""
    data = vol.data.astype(np.float64)
    x = vol.origin[0] + vol.spacing[0] * np.arange(data.shape[2])
    z = vol.origin[2] + vol.spacing[2] * np.arange(data.shape[0])
    mass = data.sum(axis=(1, 2))
    cx = (data.sum(axis=1) * x).sum(axis=1) / np.maximum(mass, 1e-9)
    return z, mass, cx


def top_of(vol, iso=127):
    """World height of the highest slice that reaches the surface level."""
    k = np.nonzero((vol.data >= iso).any(axis=(1, 2)))[0].max()
    return vol.origin[2] + vol.spacing[2] * k


def main():
    spec_path, upright_path, *bent = sys.argv[1:]
    with open(spec_path) as fh:
        spec = yaml.safe_load(fh)
    up = read_volume(upright_path)
    if not (np.allclose(up.direction, np.eye(3)) and spec.get("units") == "world"):
        sys.exit("check.py: expects an axis-aligned volume and a spec in world units")
    nz_lat = spec["capture"]["lattice"][2]
    d = layer_moves(spec, nz_lat)
    gust = d[-1, 0] / layer_move(nz_lat - 1, 1.0)[0]  # u_k is proportional to the gust
    nz = up.data.shape[0]

    def spline_at(z):  # (u, w) of the spec's full moves at world height z
        idx = (z - up.origin[2]) / up.spacing[2]
        s = np.clip((idx + 0.5) * (nz_lat - 3) / nz, 0.0, nz_lat - 3)
        return bspline(d, s)[:, [0, 2]].T

    z0, m0, c0 = slices(up)
    top0 = top_of(up)
    zfine = np.linspace(z0[0], z0[-1], 20 * nz)
    ufine, wfine = spline_at(zfine)
    failures = []
    print(f"spec {spec_path}: gust {gust:g} mm at z = {TOP:g} mm (intended u = gust * s^2, "
          f"s = (z - {ROOT:g}) / {TOP - ROOT:g}); tolerance {TOL:g} mm per slice")
    for item in bent:
        path, frac = item.rsplit(":", 1)
        f = float(frac)
        vol = read_volume(path)
        z1, m1, c1 = slices(vol)
        # each bent slice came from the upright height z with z + f w(z) = z1
        zsrc = np.interp(z1, zfine + f * wfine, zfine)
        u_spl = f * np.interp(zsrc, zfine, ufine)
        ok = (m1 > MIN_MASS * m1.max()) & (np.interp(zsrc, z0, m0) > MIN_MASS * m0.max())
        ok &= (zsrc >= z0[0]) & (zsrc <= top0)
        moved = c1 - np.interp(zsrc, z0, c0)
        err = np.abs(moved - u_spl)[ok]
        s = np.clip((zsrc - ROOT) / (TOP - ROOT), 0.0, None)
        u_int = f * gust * s ** 2
        top1 = top_of(vol)
        w_top = f * np.interp(top0, zfine, wfine)
        print(f"\n{path} ({f:g} of the gust): per-slice error max {err.max():.2f} mm, "
              f"rms {np.sqrt((err ** 2).mean()):.2f} mm over {ok.sum()} slices; "
              f"top {top0:.1f} -> {top1:.1f} mm (spline: {w_top:+.1f} mm)")
        print(f"{'height (mm)':>12} {'measured':>9} {'spline':>7} {'intended':>8}   (downwind move, mm)")
        bands = []
        for lo in np.arange(0.0, top0, BAND):
            sel = ok & (zsrc >= lo) & (zsrc < lo + BAND)
            if not sel.any():
                continue
            row = (lo, moved[sel].mean(), u_spl[sel].mean(), u_int[sel].mean())
            bands.append(row)
            print(f"{lo:5.0f}-{lo + BAND:<5.0f}  {row[1]:9.2f} {row[2]:7.2f} {row[3]:8.2f}")
        if err.max() > TOL:
            failures.append(f"{path}: a slice is {err.max():.2f} mm off the spline (> {TOL:g})")
        base = np.abs(moved[ok & (zsrc < ROOT)])
        if base.size and base.max() > 0.5:
            failures.append(f"{path}: the base moved {base.max():.2f} mm (> 0.5)")
        for a, b in zip(bands, bands[1:], strict=False):
            if b[1] < a[1] - 0.3:
                failures.append(f"{path}: the move shrinks from {a[1]:.2f} mm at {a[0]:g} mm to "
                                f"{b[1]:.2f} mm at {b[0]:g} mm")
        hi = np.nonzero(ok)[0].max()
        want = f * gust * ((zsrc[hi] - ROOT) / (TOP - ROOT)) ** 2
        print(f"top slice (from z = {zsrc[hi]:.1f} mm): moved {moved[hi]:.2f} mm, intended {want:.2f} mm")
        if abs(moved[hi] - want) > 0.1 * f * gust:
            failures.append(f"{path}: the top moved {moved[hi]:.2f} mm, intended {want:.2f} mm")
        if abs((top1 - top0) - w_top) > 1.5 * up.spacing[2]:
            failures.append(f"{path}: the top came down {top0 - top1:.1f} mm, the spline says "
                            f"{-w_top:.1f} mm")
    if failures:
        print("\nFAILED:\n  " + "\n  ".join(failures))
        sys.exit(1)
    print("\nOK: base fixed, the move grows with height to the intended top displacement")


if __name__ == "__main__":
    main()
