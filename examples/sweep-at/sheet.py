"""Tile renders into one titled picture: python sheet.py OUT.png 'title|title|...' A.png B.png ..."""

import sys

from volwarp_cli.io.images import read_image, write_image
from volwarp_cli.render.sheet import contact_sheet

out, titles, *pictures = sys.argv[1:]
images = [read_image(p)[..., :3] for p in pictures]
write_image(out, contact_sheet(images, columns=len(images), background=0.0,
                               titles=titles.split("|")))
