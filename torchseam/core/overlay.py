"""Text drawn on camera frames that stays readable on any background.

White text alone vanishes on a white arc flash and dark text on a dark frame, so every label
is drawn twice: a thick dark outline first, then the text itself on top of it.
"""

from __future__ import annotations

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
OUTLINE_BGR = (0, 0, 0)


def put_label(img: np.ndarray, text: str, org: tuple[int, int], scale: float,
              colour: tuple[int, int, int] = (255, 255, 255), thickness: int = 1) -> np.ndarray:
    """Draw ``text`` on ``img`` (in place; BGR or grey) at ``org`` (bottom-left of the text, px)
    with ``cv2.FONT_HERSHEY_SIMPLEX`` at ``scale``, in ``colour`` over a dark outline two
    pixels wider than the strokes. Returns ``img``."""
    org = (int(org[0]), int(org[1]))
    dark: tuple[int, ...] = OUTLINE_BGR
    light: tuple[int, ...] = tuple(int(c) for c in colour)
    if img.ndim == 2:  # grey: one channel, the colour's luminance
        dark = (0,)
        light = (int(round(0.114 * light[0] + 0.587 * light[1] + 0.299 * light[2])),)
    cv2.putText(img, text, org, FONT, scale, dark, thickness + 2, cv2.LINE_AA)
    cv2.putText(img, text, org, FONT, scale, light, thickness, cv2.LINE_AA)
    return img
