"""Which way the stripe runs in a camera frame, from the stripe itself.

A stripe along the rows gives one centre-line point per column over its whole length; turned a
quarter, the same stripe runs along the columns, where TIPM's ridge filter (the response minus
its mean over ``ridge_px`` rows) takes most of it away and its centre line covers only the
columns the stripe crosses. So the view whose centre line covers more columns is the one the
stripe runs along. This looks at the stripe's own extent, not at whether a view happens to
yield a corner: a corner can be found in the wrong view (a flank of a groove, a bright edge
beside the stripe taken for an arm), and a stripe without a corner (a butt joint) has none in
either.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from torchseam.core.orient import FrameView


class StripeReader(Protocol):
    """What :func:`stripe_axis` needs of TIPM (:class:`~torchseam.vision.tipm.Tipm`)."""

    def stripe_mask(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]: ...

    def centre(self, response: np.ndarray, mask: np.ndarray) -> np.ndarray: ...


def stripe_extent(frame: np.ndarray, tipm: StripeReader) -> int:
    """How many columns of ``frame`` (H, W[, 3]) the stripe's centre line covers, read as
    TIPM reads a frame (the stripe along the rows)."""
    red, mask, why = tipm.stripe_mask(np.ascontiguousarray(frame))
    if why:
        return 0
    return len(tipm.centre(red, mask))


def stripe_axis(frame: np.ndarray, tipm: StripeReader, response: str = "red") -> str | None:
    """``"rows"`` or ``"columns"``: which way the stripe runs in a camera frame (H, W[, 3]);
    None when neither view shows a stripe (not a clean frame: try the next one).

    Example:
        >>> from torchseam.vision.tipm import load_tipm
        >>> img = np.zeros((120, 160), np.uint8)
        >>> img[:, 70:73] = 200          # a stripe down the columns
        >>> stripe_axis(img, load_tipm())
        'columns'
    """
    h = frame.shape[0]
    extent = {axis: stripe_extent(FrameView(axis, h, response).frame(frame), tipm)
              for axis in ("rows", "columns")}
    best = max(extent, key=lambda a: extent[a])
    return best if extent[best] > 0 else None
