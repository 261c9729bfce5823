"""Regenerate the small synthetic test volumes in this folder (deterministic).

    python tests/data/make_samples.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

HERE = Path(__file__).parent


def ball_volume() -> Volume:
    """30^3 uint8: a ball of radius 10 voxels (value 200) in a zero background."""
    n = 30
    c = (n - 1) / 2
    z, y, x = np.mgrid[:n, :n, :n]
    data = np.where((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2 <= 10.0 ** 2, 200, 0)
    return Volume(data.astype(np.uint8), spacing=(1, 1, 1), origin=(0, 0, 0), space="left-posterior-superior")


def block_volume() -> Volume:
    """An anisotropic int16 block (x 24, y 16, z 10) with a rotated direction and an offset origin.

    Values encode position (x + 30 y - 500 z) so any transposition or flip shows.
    """
    nx, ny, nz = 24, 16, 10
    z, y, x = np.mgrid[:nz, :ny, :nx]
    data = (x + 30 * y - 500 * z).astype(np.int16)
    angle = np.deg2rad(30.0)
    direction = np.array([[np.cos(angle), -np.sin(angle), 0.0],
                          [np.sin(angle), np.cos(angle), 0.0],
                          [0.0, 0.0, 1.0]])
    return Volume(data, spacing=(0.5, 0.75, 2.5), origin=(-12.5, 40.25, 7.0), direction=direction,
                  space="left-posterior-superior", meta={"description": "volwarp test block"})


if __name__ == "__main__":
    write_volume(ball_volume(), HERE / "ball_30_uint8.nrrd")
    write_volume(block_volume(), HERE / "block_int16_aniso.nrrd")
