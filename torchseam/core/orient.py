"""How the stripe shows in the camera image, and the map to the view TIPM works in.

TIPM, the trackers and ECAL follow a stripe that runs along the image rows (one centre-line
point per column). A sensor mounted at 90 degrees shows it running along the columns. Rather
than teach every stage both layouts, the frame is turned once at the boundary (a quarter turn
clockwise: ``cv2.rotate``, a fraction of a millisecond) and points are mapped back before
anything geometric (triangulation uses the camera's own pixel coordinates). Which way the V
opens needs no setting: TIPM's corner search and the trackers do not assume it.

The same boundary picks the stripe response: a colour camera's red excess ``R - max(G, B)``
(white arc light drops out) unless the stripe itself is overexposed into white (then the red
excess collapses where the stripe is brightest, and its brightness is the better response, as a
mono camera's is); see :func:`torchseam.vision.tipm.find_view`. The brightness of a colour frame
is the mean of its three channels, not the red channel alone: such a stripe clips R first, and
where arc glare clips R (and G) around it the stripe still shows in the channels that have not
clipped, so the mean keeps a contrast where R has none.

Pixel coordinates are (u, v) = (column, row) with pixel centres on integers, so the maps are
exact. For a camera image of height ``H`` turned clockwise (``"columns"``)::

    u_c = H - 1 - v,   v_c = u          (camera -> canonical)
    u = v_c,           v = H - 1 - u_c  (canonical -> camera)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# the settings of ``camera.stripe_axis`` and ``camera.stripe_response`` (``auto`` and the two
# views below) are STRIPE_AXES and STRIPE_RESPONSES in :mod:`torchseam.core.config`, which the
# command line's parsers read without importing OpenCV


#: the brightness of a BGR frame (``cv2.transform``'s (1, 3) matrix): the channels' mean
BRIGHTNESS = np.full((1, 3), 1.0 / 3.0, np.float32)


@dataclass(frozen=True)
class FrameView:
    """How TIPM and the trackers see a camera image of ``height`` rows: the stripe's
    direction, ``"rows"`` (as TIPM works) or ``"columns"`` (the frame is turned a quarter
    clockwise first), and its response, ``"red"`` (a colour frame as it is: TIPM takes the red
    excess) or ``"intensity"`` (a colour frame's brightness, the mean of its channels, read
    like a mono frame).

    Example:
        >>> ax = FrameView("columns", height=4)
        >>> ax.to_canonical(np.array([1.0, 0.0]))
        array([3., 1.])
        >>> ax.to_camera(ax.to_canonical(np.array([1.0, 0.0])))
        array([1., 0.])
    """

    axis: str = "rows"
    height: int = 0
    response: str = "red"

    def __post_init__(self) -> None:
        if self.axis not in ("rows", "columns"):
            raise ValueError(f"stripe axis {self.axis!r}: use rows or columns")
        if self.response not in ("red", "intensity"):
            raise ValueError(f"stripe response {self.response!r}: use red or intensity")

    @property
    def turned(self) -> bool:
        return self.axis == "columns"

    def frame(self, img: np.ndarray) -> np.ndarray:
        """The frame (H, W[, 3]) as TIPM reads it (the same array when nothing changes)."""
        if self.response == "intensity" and img.ndim == 3:
            img = cv2.transform(img, BRIGHTNESS)  # (B + G + R) / 3, rounded
        if not self.turned:
            return img
        if img.shape[0] != self.height:
            raise ValueError(f"frame has {img.shape[0]} rows; the stripe axis was set for "
                             f"{self.height}")
        return cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)

    def to_canonical(self, uv: np.ndarray) -> np.ndarray:
        """Camera pixels (..., 2) -> the turned frame's pixels."""
        uv = np.asarray(uv, float)
        if not self.turned:
            return uv
        return np.stack([self.height - 1 - uv[..., 1], uv[..., 0]], axis=-1)

    def to_camera(self, uv: np.ndarray) -> np.ndarray:
        """The turned frame's pixels (..., 2) -> camera pixels."""
        uv = np.asarray(uv, float)
        if not self.turned:
            return uv
        return np.stack([uv[..., 1], self.height - 1 - uv[..., 0]], axis=-1)

    def direction_to_camera(self, d: np.ndarray) -> np.ndarray:
        """Image directions (..., 2) of the turned frame -> the camera image's."""
        d = np.asarray(d, float)
        if not self.turned:
            return d
        return np.stack([d[..., 1], -d[..., 0]], axis=-1)
