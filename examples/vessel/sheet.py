"""The vessel figure: kinked | straightened, as surfaces and as angiograms.

    python sheet.py OUT.png --renders KINKED.png STRAIGHT.png --mip KINKED.nrrd STRAIGHT.nrrd

Top row: the two `volwarp mesh --render` pictures, side by side. Bottom row:
maximum-intensity projections of the two volumes along y (the view of the
renders, x to the right, z up), the way an angiogram is looked at, scaled to
the renders' height. The volumes must share one grid (`volwarp warp --crop`).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import zoom

from volwarp_cli.io import read_volume
from volwarp_cli.io.images import read_image, write_image
from volwarp_cli.render.sheet import contact_sheet


def rgb(image):
    image = np.asarray(image, dtype=np.float32)
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    return image[:, :, :3]


def mip(path, height):
    vol = read_volume(path)
    proj = vol.data.max(axis=1).astype(np.float32)[::-1] / 255.0  # rows: z, top = high z
    f = height / (proj.shape[0] * vol.spacing[2])  # pixels per world unit
    big = np.clip(zoom(proj, (f * vol.spacing[2], f * vol.spacing[0]), order=1), 0.0, 1.0)
    return rgb(big[:, :, None])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("output")
    ap.add_argument("--renders", nargs="+", required=True)
    ap.add_argument("--mip", nargs="+", required=True)
    args = ap.parse_args()
    if len(args.renders) != len(args.mip):
        raise SystemExit("give as many volumes (--mip) as renders")

    renders = [rgb(read_image(p)) for p in args.renders]
    height = max(r.shape[0] for r in renders)
    images = renders + [mip(p, height) for p in args.mip]
    write_image(args.output, contact_sheet(images, columns=len(renders), background=1.0))


if __name__ == "__main__":
    main()
