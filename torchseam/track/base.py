"""The typed hand-off from a tracker to the stages after it: :class:`TrackResult` per frame,
and :class:`Tracker`, the base every tracker the CLI and the live loop drive derives from.

A tracker's per-frame word is its point and a status decided from image evidence, with the
evidence itself (the TIPM corner it weighed) and what it already computed on the frame that a
later stage can reuse (the stripe window for ECAL, the arm directions). The locator reads
these fields; it never probes a tracker for optional attributes.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class TrackStatus(IntEnum):
    """Per-frame status codes (int64 tensors hold these values)."""

    TRACKED = 0
    COASTING = 1
    LOST = 2


@dataclass(frozen=True)
class Fix:
    """A TIPM corner a tracker weighed on one frame.

    Attributes:
        uv: (2,) the corner, frame px. cov: (2, 2) its covariance before the glare term;
            inflate: the glare term's factor on it (1: no glare).
        taken: whether the filter took it (or restarted on it).
        seen: the stripe is seen at the corner: both arms have centre-line points next to it
            (not a corner extrapolated from arms that stop short: glare or a gap over it).
        shallow: the corner was read from the slope break of a nearly straight stripe
            (:func:`~torchseam.track.shallow.shallow_corner`, where TIPM gives none): weak
            along the stripe (``cov`` says how weak), not a TIPM corner.
        firm: precise enough to place the seam by (the live loop's located points for the
            robot's expected pixel): a TIPM corner; a shallow one only when its std along
            the stripe, glare term included, is within the tracker's ``evidence_px``.
        jumped: the filter started again on it (a clean corner its gate refused: the image
            jumped, or glare made a corner elsewhere): no evidence on its own frame, only
            once the next frame's corner is found there.
    """

    uv: np.ndarray
    cov: np.ndarray
    inflate: float
    taken: bool
    seen: bool = True
    shallow: bool = False
    firm: bool = True
    jumped: bool = False


@dataclass(frozen=True)
class TrackResult:
    """What a tracker says about one frame.

    Attributes:
        uv: (2,) the point, frame px (NaN: none).
        status: :class:`~torchseam.track.fusion.TrackStatus` value: ``TRACKED`` only with
            evidence in the image at the point, ``COASTING`` when predicted, ``LOST``.
        fix: the TIPM corner weighed on the frame (the evidence), or None.
        stripe: ``(response, mask, (x0, y0))`` of the tracker's TIPM window on this frame, or
            None; valid until the tracker's next frame (the arrays are reused).
        arm_dirs: (2, 2) unit image directions of the left and right arm at the corner from a
            clean fix on this frame, or None.
        glare: the red glare around the predicted point (grey levels; 0 when not measured).

    Example:
        >>> TrackResult(np.array([10.0, 20.0]), int(TrackStatus.COASTING)).tracked
        False
    """

    uv: np.ndarray
    status: int
    fix: Fix | None = None
    stripe: tuple[np.ndarray, np.ndarray, tuple[int, int]] | None = None
    arm_dirs: np.ndarray | None = None
    glare: float = 0.0

    @property
    def tracked(self) -> bool:
        return self.status == TrackStatus.TRACKED


class Tracker:
    """Base of the trackers: ``init(frame, uv)`` on the first frame, then ``track(frame) ->
    TrackResult`` (or ``update(frame) -> (uv, status)``, the same without the evidence) per
    frame; ``expect(uv)`` before a frame where the caller knows where the point should be
    (the robot's motion), ``idle()`` between frames (work for the next one, after the
    frame's command is out). The defaults do nothing; a tracker overrides what it has."""

    name = ""
    #: frames per second its motion model was fitted at (None: nothing fitted per frame)
    fitted_fps: float | None = None

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        raise NotImplementedError

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        raise NotImplementedError

    def track(self, frame: np.ndarray) -> TrackResult:
        uv, status = self.update(frame)
        return TrackResult(np.asarray(uv, float), int(status))

    def expect(self, uv: np.ndarray | None) -> None:
        """Where the point should be in the next frame (None: no idea); ignored by default."""

    def idle(self) -> None:
        """Work between frames; none by default."""
