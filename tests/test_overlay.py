"""Overlay labels read on a white arc flash and on a dark frame."""

import numpy as np

from torchseam.core.overlay import put_label


def test_label_outlined_on_white_and_black():
    white = np.full((40, 200, 3), 255, np.uint8)
    put_label(white, "TIPM (1.0, 2.0)", (6, 20), 0.5)
    assert (white.max(axis=2) < 60).sum() > 50       # the dark outline shows on white
    black = np.zeros((40, 200, 3), np.uint8)
    put_label(black, "TIPM (1.0, 2.0)", (6, 20), 0.5)
    assert (black.min(axis=2) > 200).sum() > 20      # the white text shows on black


def test_label_on_grey_frame():
    grey = np.full((40, 200), 255, np.uint8)
    out = put_label(grey, "lost", (6, 20), 0.5, colour=(0, 200, 255))
    assert out is grey and grey.ndim == 2 and grey.min() < 60
