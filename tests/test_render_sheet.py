"""Contact sheets: placement of each picture, mixed sizes, refusals."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.render.sheet import contact_sheet


def test_tiles_row_by_row_with_gaps():
    ims = [np.full((3, 5, 3), v, np.uint8) for v in (10, 20, 30)]
    sheet = contact_sheet(ims, columns=2, gap=1, background=0)
    assert sheet.shape == (2 * 3 + 3, 2 * 5 + 3, 3)
    assert (sheet[1:4, 1:6] == 10).all() and (sheet[1:4, 7:12] == 20).all()
    assert (sheet[5:8, 1:6] == 30).all()
    assert (sheet[5:8, 7:12] == 0).all()  # empty cell
    assert (sheet[0] == 0).all() and (sheet[:, 6] == 0).all()  # gaps


def test_smaller_pictures_are_centred_in_their_cell():
    big = np.full((6, 8, 1), 1.0, np.float32)
    small = np.full((2, 4, 1), 2.0, np.float32)
    sheet = contact_sheet([big, small], columns=2, gap=0, background=0.0)
    assert sheet.shape == (6, 16, 1)
    cell = sheet[:, 8:, 0]
    assert (cell[2:4, 2:6] == 2.0).all()
    assert cell.sum() == 2.0 * 8  # nothing else drawn in the cell


def test_default_layout_is_near_square():
    ims = [np.zeros((2, 2, 3), np.uint8)] * 5
    assert contact_sheet(ims, gap=0).shape == (2 * 2, 3 * 2, 3)


def test_refuses_mixed_channels_and_empty():
    with pytest.raises(VolwarpError, match="image 1"):
        contact_sheet([np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2, 4), np.uint8)])
    with pytest.raises(VolwarpError):
        contact_sheet([])
