"""The real-scan figure: before | after, as surfaces and as a coronal slice.

    python figure.py OUT.png --spec SPEC.yaml --views 'AZ,EL;AZ,EL' --tile PIXELS \
        --meshes BEFORE.ply AFTER.ply [AFTER2.ply ...] \
        [--slice-y Y --slices scan:BEFORE.nrrd scan:AFTER.nrrd sdf:AFTER2.nrrd ...]

One row per view: the meshes side by side, all drawn by the same camera
(fitted to all of them). `volwarp mesh --render` fits its camera to each mesh
alone, so a raised crown would only shrink that picture; here sizes compare.
Then, with --slice-y, one row of coronal slices through the volumes at world
y = Y (LPS mm), resampled on one common world grid: `scan:` volumes in grey,
`sdf:` (signed distance fields, mm, negative inside) in blue inside / red
outside with 10 mm bands and the zero level in black.

Marks: the spec's drag handles, a red dot at each `from` point in the first
column and at each `to` point in the others, with a blue line back to `from`;
the first column's outline (and on slices, its skin contour) dashed over the
others, so every change shows against the original.
"""

from __future__ import annotations

import argparse

import numpy as np
import yaml
from scipy.ndimage import binary_erosion, binary_fill_holes, label, map_coordinates

from volwarp_cli.io import read_volume
from volwarp_cli.io.images import write_image
from volwarp_cli.render.sheet import contact_sheet
from volwarp_cli.render.surface import fit_camera, render_mesh
from volwarp_cli.surface.mesh_io import read_mesh

SKIN = "skin"
MARK = np.array([200, 30, 30], dtype=np.uint8)
GHOST = np.array([40, 90, 200], dtype=np.uint8)
OUTLINE = np.array([40, 40, 40], dtype=np.uint8)
SLICE_OUTLINE = np.array([255, 210, 0], dtype=np.uint8)
WHITE = (255, 255, 255)
ISO = 40.0  # the skin level of the scan (as in the Makefile)
GAP = 4  # pixels between tiles


def disc(img, xy, color, r):
    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    d = np.hypot(xx - xy[0], yy - xy[1])
    img[d <= r + 1.5] = 255  # white rim
    img[d <= r] = color


def segment(img, a, b, color, width):
    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    ab = b - a
    t = np.clip(((xx - a[0]) * ab[0] + (yy - a[1]) * ab[1]) / max(ab @ ab, 1e-9), 0, 1)
    img[np.hypot(xx - (a[0] + t * ab[0]), yy - (a[1] + t * ab[1])) <= width] = color


def dashed_edge(mask, r):
    """Pixels of a dashed line along the border of ``mask``."""
    edge = mask & ~binary_erosion(mask, iterations=max(1, round(r / 2.5)))
    yy, xx = np.nonzero(edge)
    keep = ((xx + yy) // int(2.5 * r)) % 3 != 2
    return yy[keep], xx[keep]


def mark(img, col, handles, to_pixels, r):
    for src, dst in handles:
        a, b = to_pixels(np.stack([src, dst]))
        if a is None:
            continue
        if col == 0:
            disc(img, a, MARK, r)
        else:
            segment(img, a, b, GHOST, r / 3)
            disc(img, a, GHOST, r * 0.6)
            disc(img, b, MARK, r)


def surface_row(meshes, view, size, handles, r):
    allv = np.concatenate([m.vertices for m in meshes])
    centre = 0.5 * (allv.min(axis=0) + allv.max(axis=0))
    camera = fit_camera(allv, view, size, margin=0.04)
    visible = [(s, d) for s, d in handles  # on the near side of the head (or its outline)
               if np.dot(s - centre, camera.back) > -0.15 * np.linalg.norm(s - centre)]

    def to_pixels(points):
        p = points - camera.center
        return np.stack([p @ camera.right * camera.scale + 0.5 * size[0],
                         0.5 * size[1] - p @ camera.up * camera.scale], axis=1)

    tiles = []
    for col, mesh in enumerate(meshes):
        img = np.array(render_mesh(mesh, camera=camera, color=SKIN, background=WHITE))
        if col == 0:
            outline = dashed_edge(np.any(img != np.array(WHITE, np.uint8), axis=-1), r)
        else:
            img[outline] = OUTLINE
        mark(img, col, visible, to_pixels, r)
        tiles.append(img)
    return tiles


def head_mask(inside):
    """The largest piece of ``inside``, holes filled: the head's outer contour only."""
    labels, n = label(inside)
    if n == 0:
        return inside
    biggest = 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    return binary_fill_holes(labels == biggest)


def slice_row(volumes, y, lo, hi, size, handles, r):
    """Coronal slices at world y: x to the right as seen from the front (patient's left on the right)."""
    w, h = size
    span = max(hi[0] - lo[0], hi[1] - lo[1])
    mid = 0.5 * (lo + hi)
    step = span / min(w, h)
    xs = mid[0] + (np.arange(w) - 0.5 * (w - 1)) * step
    zs = mid[1] - (np.arange(h) - 0.5 * (h - 1)) * step  # image rows go down, z goes up
    X, Z = np.meshgrid(xs, zs)
    world = np.stack([X.ravel(), np.full(X.size, y), Z.ravel()], axis=1)
    near = [(s, d) for s, d in handles if abs(s[1] - y) < 2.0 and abs(d[1] - y) < 2.0]

    def to_pixels(points):
        return np.stack([(points[:, 0] - xs[0]) / step, (zs[0] - points[:, 2]) / step], axis=1)

    tiles = []
    for col, (kind, vol) in enumerate(volumes):
        idx = vol.world_to_index(world)[:, ::-1].T  # z y x voxel indices
        outside = 0.0 if kind == "scan" else float(vol.data.max())
        v = map_coordinates(vol.data.astype(np.float32), idx, order=1, mode="constant",
                            cval=outside).reshape(h, w)
        if kind == "scan":
            g = np.clip(v / 160.0, 0, 1) * 255
            img = np.repeat(g[..., None], 3, axis=2).astype(np.uint8)
            inside = v >= ISO
        else:  # signed distance: blue inside, red outside, 10 mm bands, zero level black
            t = np.clip(np.abs(v) / 40.0, 0, 1)
            band = 0.85 + 0.15 * (np.floor(np.abs(v) / 10.0) % 2)
            base = np.where(v[..., None] < 0, [60, 110, 230], [230, 90, 60]).astype(np.float32)
            img = (255 - (255 - base) * (0.35 + 0.65 * t[..., None])) * band[..., None]
            img = img.astype(np.uint8)
            inside = v < 0
            img[inside & ~binary_erosion(inside)] = 0
        if col == 0:
            outline = dashed_edge(head_mask(inside), r)
        else:
            img[outline] = SLICE_OUTLINE
        mark(img, col, near, to_pixels, r)
        tiles.append(img)
    return tiles


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--spec", required=True)
    ap.add_argument("--views", required=True)
    ap.add_argument("--tile", type=int, default=300)
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--slice-y", type=float)
    ap.add_argument("--slices", nargs="+", default=[])
    ap.add_argument("--labels", help="column titles, separated by |")
    ap.add_argument("--levels", type=int, default=64,
                    help="grey levels per colour channel (fewer: a smaller PNG)")
    args = ap.parse_args()

    with open(args.spec) as fh:
        spec = yaml.safe_load(fh)
    handles = [(np.array(h["from"], float), np.array(h["to"], float))
               for st in spec["steps"] for h in st.get("drag", [])]
    size = (args.tile, args.tile)
    r = max(2.0, args.tile / 70)
    meshes = [read_mesh(p) for p in args.meshes]
    tiles = []
    for view in args.views.split(";"):
        az, el = (float(v) for v in view.split(","))
        tiles += surface_row(meshes, (az, el), size, handles, r)
    if args.slices:
        vols = [(s.split(":", 1)[0], read_volume(s.split(":", 1)[1])) for s in args.slices]
        allv = np.concatenate([m.vertices for m in meshes])
        lo, hi = allv.min(axis=0)[[0, 2]] - 8.0, allv.max(axis=0)[[0, 2]] + 8.0
        tiles += slice_row(vols, args.slice_y, lo, hi, size, handles, r)
    n = len(meshes)  # titles over the first row's columns only
    titles = args.labels.split("|") if args.labels else None
    sheet = contact_sheet(tiles[:n], columns=n, titles=titles, gap=GAP)
    if len(tiles) > n:
        sheet = np.concatenate([sheet, contact_sheet(tiles[n:], columns=n, gap=GAP)[GAP:]])
    q = 256 // args.levels  # posterise: smooth shading compresses far better
    sheet = np.minimum((sheet // q) * q + q // 2, 255).astype(np.uint8)
    write_image(args.out, sheet)


if __name__ == "__main__":
    main()
