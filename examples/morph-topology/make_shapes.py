"""Write the example's two shapes: a ball and a torus, smooth 0..1 densities.

    python make_shapes.py OUT_DIR [--size N]

Both are sampled from analytic signed distances through a logistic ramp one
voxel wide, so ``volwarp`` sees smooth samples and places their surfaces with
sub-voxel accuracy (iso level 0.5, inside above). World units are millimetres,
spacing 1 mm, the grid centred on the origin.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


def grid(n: int):
    c = (n - 1) / 2.0
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64) - c
    return x, y, z, (-c, -c, -c)


def density(sdf: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(sdf / 0.6))).astype(np.float32)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args(argv)
    n = args.size
    x, y, z, origin = grid(n)
    s = n / 64.0
    ball = np.sqrt(x**2 + y**2 + z**2) - 18.0 * s
    ring = np.sqrt((np.sqrt(x**2 + y**2) - 17.0 * s) ** 2 + z**2) - 7.0 * s
    args.out.mkdir(parents=True, exist_ok=True)
    write_volume(Volume(density(ball), origin=origin), args.out / "ball.nrrd")
    write_volume(Volume(density(ring), origin=origin), args.out / "torus.nrrd")


if __name__ == "__main__":
    main()
