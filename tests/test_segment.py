"""Binary segmentation of real photos (scene/segment.py): morphology and border clearing on masks whose
pixel counts are known by construction."""

from __future__ import annotations

import numpy as np

from dualsight.scene.segment import binarize, clear_border, morphology, score_image


def test_opening_and_closing_change_the_pixel_count_as_expected():
    """A 40x40 square with a 3x3 hole, a 1-px wide tail and a 2x2 speck: opening (3x3) removes the tail and
    the speck exactly, closing (5x5) fills the hole exactly; a 4-px gap is bridged by a 5x5 closing only."""
    m = np.zeros((80, 100), np.uint8)
    m[20:60, 20:60] = 1
    m[38:41, 38:41] = 0                                        # hole: 9 px
    m[30, 60:80] = 1                                           # tail: 20 px
    m[5:7, 5:7] = 1                                            # speck: 4 px
    assert m.sum() == 1600 - 9 + 20 + 4
    assert morphology(m, open_px=3).sum() == 1600 - 9
    assert morphology(m, open_px=3, close_px=5).sum() == 1600
    assert morphology(m, close_px=5).sum() >= 1600 + 20     # closing alone keeps the tail
    assert morphology(m, open_px=1, close_px=1).sum() == m.sum()    # K <= 1: off
    two = np.zeros((40, 60), np.uint8)
    two[10:30, 10:25] = 1
    two[10:30, 29:44] = 1                                      # 4-px gap (columns 25..28)
    assert morphology(two, close_px=5).sum() == 20 * 34
    assert morphology(two, close_px=3).sum() == 2 * 300
    b = clear_border(np.ones((10, 12), np.uint8), 2)
    assert b.sum() == 6 * 8


def test_score_is_the_largest_channel_and_inversion_its_smallest():
    rgb = np.array([[[10, 200, 30], [255, 0, 0]]], np.uint8)
    np.testing.assert_array_equal(score_image(rgb), [[200, 255]])
    np.testing.assert_array_equal(score_image(rgb, invert=True), [[245, 255]])
    np.testing.assert_array_equal(binarize(rgb, 201), [[False, True]])
