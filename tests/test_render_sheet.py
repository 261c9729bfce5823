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


def test_titles_are_written_above_each_picture():
    ims = [np.full((40, 120, 3), 200, np.uint8), np.full((30, 80, 3), 90, np.uint8)]
    plain = contact_sheet(ims, columns=2, gap=2, background=255)
    sheet = contact_sheet(ims, columns=2, gap=2, background=255, titles=["t = 0.00", "t = 1"])
    strip = max(16, 120 // 12)
    assert sheet.shape == (plain.shape[0] + strip, plain.shape[1], 3)
    # the pictures sit below their strips, unchanged
    assert (sheet[2 + strip:2 + strip + 40, 2:122] == 200).all()
    # text: dark pixels in each title strip, centred over its cell, none elsewhere in it
    for cell_x in (2, 124):
        title = sheet[2:2 + strip, cell_x:cell_x + 120].min(axis=2)
        ink = np.nonzero((title < 128).any(axis=0))[0]
        assert ink.size > 5
        assert abs((ink.min() + ink.max()) / 2 - 60) < 8
    with pytest.raises(VolwarpError, match="titles"):
        contact_sheet(ims, titles=["one"])


def test_titles_on_float_pictures_and_dark_backgrounds():
    ims = [np.zeros((20, 48, 1), np.float32)] * 2
    sheet = contact_sheet(ims, background=0.0, titles=["a", "b"], gap=0)
    assert sheet.dtype == np.float32 and sheet.shape == (20 + 16, 96, 1)
    assert sheet[:16].max() > 0.5  # light ink on the dark strip
    assert (sheet[16:] == 0).all()


def test_titles_on_rgba_pictures_are_opaque_ink():
    ims = [np.zeros((20, 120, 4), np.uint8)] * 2
    sheet = contact_sheet(ims, background=255, titles=["frame one", "two"], gap=0)
    strip = sheet[:16]
    assert (strip[..., 3] == 255).all()  # opaque, text or not
    assert (strip[..., :3] < 128).any(axis=2).sum() > 20  # dark ink on the white strip
