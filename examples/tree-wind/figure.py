"""The tree-in-the-wind figure: the tree's surfaces side by side, one camera for all.

    python figure.py OUT.png --view AZ,EL --tile WxH \
        --meshes A.ply B.ply ... --labels LEAF_A.nrrd LEAF_B.nrrd ... [--titles 'a|b|...']

`volwarp mesh --render` fits its camera to each mesh alone, so a bent tree (wider)
would come out smaller than the upright one; here every tile is drawn by the same
orthographic camera, fitted to all the meshes, and the ground stays at one height.

Colours: each triangle is foliage (green) or wood (brown) by the label volume of
its own mesh (make_tree.py's LEAF.nrrd, warped like the tree), sampled at its
corners, and drawn with the renderer's per-triangle colours. The first tile's
outline is dashed in the others where they leave it, so the bend shows against
the upright tree.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import binary_dilation, binary_erosion, map_coordinates

from volwarp_cli.io import read_volume
from volwarp_cli.io.images import write_image
from volwarp_cli.render.sheet import contact_sheet
from volwarp_cli.render.surface import fit_camera, render_mesh
from volwarp_cli.surface.mesh import Mesh
from volwarp_cli.surface.mesh_io import read_mesh

LEAF = (0.30, 0.56, 0.22)
WOOD = (0.50, 0.34, 0.20)
WHITE = (1.0, 1.0, 1.0)
OUTLINE = np.array([50, 50, 50], dtype=np.uint8)


def wood_faces(mesh: Mesh, label_path: str) -> np.ndarray:
    """True for the triangles whose corners are wood (label below half) on average."""
    vol = read_volume(label_path)
    idx = vol.world_to_index(mesh.vertices)[:, ::-1].T  # z y x voxel indices
    leaf = map_coordinates(vol.data.astype(np.float32), idx, order=1, mode="nearest") / 255.0
    return leaf[mesh.faces].mean(axis=1) < 0.5


def two_tone(mesh: Mesh, wood: np.ndarray, camera) -> np.ndarray:
    """``mesh`` rendered in LEAF, with its ``wood`` triangles in WOOD."""
    colors = np.where(wood[:, None], WOOD, LEAF)
    return render_mesh(mesh, camera=camera, face_colors=colors, background=WHITE)


def dashed_edge(mask, r):
    """Pixels of a dashed line along the border of ``mask``."""
    edge = mask & ~binary_erosion(mask, iterations=max(1, round(r / 2.5)))
    yy, xx = np.nonzero(edge)
    keep = ((xx + yy) // int(2.5 * r)) % 3 != 2
    return yy[keep], xx[keep]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--view", default="-90,10", help="azimuth,elevation (degrees, z up)")
    ap.add_argument("--tile", default="300x400", help="tile size WxH")
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--labels", nargs="+", required=True, help="one leaf label volume per mesh")
    ap.add_argument("--titles", help="column titles, separated by |")
    ap.add_argument("--levels", type=int, default=64,
                    help="grey levels per colour channel (fewer: a smaller PNG)")
    args = ap.parse_args()
    if len(args.labels) != len(args.meshes):
        ap.error("give one --labels volume per mesh")

    view = tuple(float(v) for v in args.view.split(","))
    size = tuple(int(v) for v in args.tile.lower().split("x"))
    meshes = [read_mesh(p) for p in args.meshes]
    camera = fit_camera(np.concatenate([m.vertices for m in meshes]), view, size, margin=0.04)
    r = max(2.0, size[0] / 75)
    tiles = []
    for col, (mesh, label) in enumerate(zip(meshes, args.labels, strict=True)):
        img = two_tone(mesh, wood_faces(mesh, label), camera)
        if col == 0:
            outline = dashed_edge(np.any(img != 255, axis=-1), r)
        else:  # where the upright tree was and the bent one is not (nor next to it)
            yy, xx = outline
            near = binary_dilation(np.any(img != 255, axis=-1), iterations=2)
            empty = ~near[yy, xx]
            img[yy[empty], xx[empty]] = OUTLINE
        tiles.append(img)
    sheet = contact_sheet(tiles, columns=len(tiles),
                          titles=args.titles.split("|") if args.titles else None)
    q = 256 // args.levels  # posterise: smooth shading compresses far better
    sheet = np.minimum((sheet // q) * q + q // 2, 255).astype(np.uint8)
    write_image(args.out, sheet)


if __name__ == "__main__":
    main()
