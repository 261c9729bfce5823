"""Tile PNG renders side by side into one picture.

    python sheet.py OUT.png A.png B.png ...
"""

import sys

from volwarp_cli.io.images import read_image, write_image
from volwarp_cli.render.sheet import contact_sheet

out, *paths = sys.argv[1:]
images = [read_image(p) for p in paths]
write_image(out, contact_sheet(images, columns=len(images)))
