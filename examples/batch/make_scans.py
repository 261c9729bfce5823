"""Write a folder of small synthetic 'scans' for the batch example (deterministic).

    python make_scans.py scans        # scans/patient01.nrrd, scans/site-b/patient03.nrrd, ...

Each scan is a 40^3 uint8 head-like ellipsoid (skull shell + brain) with a
little blur and noise, 2 mm voxels; sizes differ a little from scan to scan.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

SCANS = {
    "patient01.nrrd": (15.0, 13.0, 16.0),
    "patient02.nrrd": (14.0, 12.5, 15.0),
    "site-b/patient03.nrrd": (16.0, 13.5, 16.5),
}


def head(radii, seed: int) -> np.ndarray:
    n = 40
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    c = (n - 1) / 2
    r = np.sqrt(((x - c) / radii[0]) ** 2 + ((y - c) / radii[1]) ** 2 + ((z - c) / radii[2]) ** 2)
    vol = np.where(r < 0.85, 120.0, 0.0) + np.where((r >= 0.85) & (r < 1.0), 220.0, 0.0)
    vol = ndimage.gaussian_filter(vol, 1.0)  # the partial-volume blur of a real scanner
    vol += np.random.default_rng(seed).normal(0, 2, vol.shape)
    return np.clip(vol, 0, 255).astype(np.uint8)


def main(folder: str) -> None:
    root = Path(folder)
    for seed, (name, radii) in enumerate(SCANS.items()):
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        write_volume(Volume(head(radii, seed), spacing=(2, 2, 2), origin=(-39, -39, -39),
                            space="left-posterior-superior"), path)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "scans")
