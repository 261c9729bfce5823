"""Write the clay block of the thesis' Figures 11-12: a 30^3 uint8 model (1 mm voxels)
holding a 18^3 block of density 255, edges softened by one voxel.

    python make_block.py block.nrrd
"""

import sys

import numpy as np
from scipy.ndimage import gaussian_filter

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

data = np.zeros((30, 30, 30), np.float32)
data[6:24, 6:24, 6:24] = 255.0
data = gaussian_filter(data, 0.7)
write_volume(Volume(np.rint(data).astype(np.uint8), space="left-posterior-superior"),
             sys.argv[1])
