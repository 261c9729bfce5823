"""The one-shot warp of a bare Scene, for tests: the whole target as one block.

(:func:`volwarp_cli.warp.blocks.warp_block` over the whole target, the
domain served by the scene's own sampler: what the command's warp computes
for its whole output on one thread.)
"""

from __future__ import annotations

import numpy as np

from volwarp_cli.bspline.pullback import DomainSampler
from volwarp_cli.warp.blocks import warp_block


def one_shot(scene) -> np.ndarray:
    """``scene``'s target for its current lattice, computed as one block."""
    sampler = scene.sampler if scene.sampler is not None else DomainSampler(scene.domain)
    return warp_block(scene, sampler, scene.target_box)
