"""Automatic exposure from the frames' own content: the next frames' exposure scale.

A band-pass mono camera has only the band the arc's glare clips: under heavy arc the glare
round the corner clips the stripe away and no image processing brings it back, while the
same frames taken at a lower exposure keep it. A cell does not know the arc level in advance,
so the weld sets the exposure itself, frame by frame, from what each frame shows round the
tracked point:

- :func:`frame_stats`: the window round the point: its *level* (the median over its columns
  of each column's brightest pixel: the stripe's peak where the stripe crosses it, the
  glare's where glare covers it) and the share of it that is *clipped*;
- :class:`ExposureController`: from those, the exposure scale of the next frame (a share of
  the camera's configured exposure, bounded by ``min_scale`` / ``max_scale``): a step down
  as soon as one frame's window clips (more than ``clip_high`` of it) or its level is over
  ``level_high``; a step up only after ``hold_frames`` frames in a row whose level stayed
  under ``level_low`` and which one step up would clip no more than ``clip_low`` of. So under
  a flickering arc the exposure is set by its brightest frames, and the bands between the
  two levels and the two clipped shares keep it from oscillating. Light that clips at any
  exposure (a weld pool flaring over the corner) is not chased down: after ``respond_steps``
  steps down in a row that each left the window's clipped share and its level within
  ``1 - respond`` of what they were (nothing changed: an arc that flickers changes them), the
  exposure goes back to where it was before those steps (they only darkened the stripe) and
  holds there until the window stops clipping. (One step is not enough to tell: an
  overexposed stripe stays clipped for a step or two before it comes under the clip.)

Both are pure (numbers in, a number out); the settings are ``configs/exposure.yaml``
(:func:`load_exposure_config`), read at the boundary.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseam.core.config import config_field, config_path, load_config


@dataclass(frozen=True)
class ExposureConfig:
    """Settings of the automatic exposure (``configs/exposure.yaml``)."""

    window_px: int = config_field(lo=4, hi=2000)
    clip_grey: float = config_field(lo=1.0, hi=255.0)
    clip_high: float = config_field(lo=0.0, hi=1.0)
    clip_low: float = config_field(lo=0.0, hi=1.0)
    level_high: float = config_field(lo=1.0, hi=255.0)
    level_low: float = config_field(lo=1.0, hi=255.0)
    step_down: float = config_field(lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    step_up: float = config_field(lo=1.0, hi=10.0, lo_open=True)
    respond: float = config_field(lo=0.0, hi=1.0)
    respond_steps: int = config_field(lo=1, hi=1000)
    hold_frames: int = config_field(lo=0, hi=100000)
    min_scale: float = config_field(lo=0.0, hi=1000.0, lo_open=True)
    max_scale: float = config_field(lo=0.0, hi=1000.0, lo_open=True)

    def _check(self) -> None:
        if self.level_low >= self.level_high:
            raise ValueError(f"level_low {self.level_low:g} must be below level_high "
                             f"{self.level_high:g} (the band between them is the hysteresis)")
        if self.clip_low > self.clip_high:
            raise ValueError(f"clip_low {self.clip_low:g} is above clip_high "
                             f"{self.clip_high:g}")
        if self.min_scale > self.max_scale:
            raise ValueError(f"min_scale {self.min_scale:g} is above max_scale "
                             f"{self.max_scale:g}")
        if self.step_up * self.level_low >= self.level_high:
            raise ValueError(f"step_up {self.step_up:g} x level_low {self.level_low:g} reaches "
                             f"level_high {self.level_high:g}: one step up would overshoot the "
                             "band and the next step down would undo it (oscillation)")


def load_exposure_config(path: str | Path | None = None) -> ExposureConfig:
    """Read ``configs/exposure.yaml`` (or ``path``)."""
    return load_config(ExposureConfig, path or config_path("exposure.yaml"))


@dataclass(frozen=True)
class FrameStats:
    """What one frame shows round the tracked point (8-bit grey levels).

    Attributes:
        level: the median over the window's columns of each column's brightest pixel.
        clipped: the share of the window's pixels at or above ``clip_grey``.
        near_clip: the share that would be at one exposure step up (``clip_grey / step_up``).
    """

    level: float
    clipped: float
    near_clip: float


def frame_stats(frame: np.ndarray, uv: np.ndarray | None, cfg: ExposureConfig) -> FrameStats:
    """:class:`FrameStats` of ``frame`` ((H, W) mono or (H, W, 3) colour, uint8 or uint16:
    a colour pixel counts by its brightest channel, 16-bit levels are read as 8-bit) in the
    window of half side ``cfg.window_px`` round ``uv`` (u, v); the whole frame when ``uv`` is
    None or not finite (no point to look round).

    Example:
        >>> cfg = ExposureConfig(40, 250.0, 0.02, 0.01, 245.0, 200.0, 0.8, 1.05, 0.9, 2, 10,
        ...                      0.3, 1.0)
        >>> f = np.zeros((100, 100), np.uint8); f[48:52] = 255; f[52] = 240
        >>> s = frame_stats(f, np.array([50.0, 50.0]), cfg)
        >>> s.level, round(s.clipped, 3), round(s.near_clip, 3)
        (255.0, 0.049, 0.062)
    """
    h, w = frame.shape[:2]
    if uv is not None and np.all(np.isfinite(uv)):
        u, v = (int(round(float(x))) for x in uv[:2])
        r = cfg.window_px
        win = frame[max(v - r, 0):min(v + r + 1, h), max(u - r, 0):min(u + r + 1, w)]
        if win.size == 0:   # the point outside the frame
            win = frame
    else:
        win = frame
    if win.ndim == 3:
        win = win.max(axis=2)
    scale = 1.0 / 257.0 if win.dtype == np.uint16 else 1.0
    level = float(np.median(win.max(axis=0))) * scale
    clipped = float(np.count_nonzero(win >= cfg.clip_grey / scale)) / win.size
    near = float(np.count_nonzero(win >= cfg.clip_grey / (scale * cfg.step_up))) / win.size
    return FrameStats(level, clipped, near)


class ExposureController:
    """The exposure scale of the next frame from each frame's :class:`FrameStats`.

    ``scale`` starts at ``start`` (default ``cfg.max_scale``: the camera's configured
    exposure) and moves by ``cfg.step_down`` / ``cfg.step_up`` per frame inside
    ``[cfg.min_scale, cfg.max_scale]`` (see the module).

    Example:
        >>> cfg = ExposureConfig(40, 250.0, 0.02, 0.01, 245.0, 200.0, 0.8, 1.05, 0.9, 2, 2,
        ...                      0.3, 1.0)
        >>> ae = ExposureController(cfg)
        >>> ae.update(FrameStats(255.0, 0.2, 0.2)), ae.update(FrameStats(150.0, 0.0, 0.0))
        (0.8, 0.8)
    """

    def __init__(self, cfg: ExposureConfig, start: float | None = None) -> None:
        self.cfg = cfg
        s = cfg.max_scale if start is None else float(start)
        self.scale = float(min(max(s, cfg.min_scale), cfg.max_scale))
        self._quiet = cfg.hold_frames   # frames in a row a step up was safe after: at once
        self._down_from: FrameStats | None = None   # the frame the last step down was for
        self._down_scale = self.scale   # the scale that frame was taken at
        self._unhelped = 0     # steps down in a row that changed nothing in the window
        self._undo_to = self.scale   # the scale before the first of them

    def update(self, stats: FrameStats) -> float:
        """Take one frame's statistics (taken at the current ``scale``); return the scale of
        the next frame (also ``self.scale``)."""
        cfg = self.cfg
        if stats.clipped > cfg.clip_high or stats.level > cfg.level_high:
            prev, self._down_from = self._down_from, stats
            prev_scale, self._down_scale = self._down_scale, self.scale
            self._quiet = 0
            tol = 1.0 - cfg.respond
            if self._unhelped < cfg.respond_steps:
                if prev is not None and (abs(stats.clipped - prev.clipped) <= tol * prev.clipped
                                         and abs(stats.level - prev.level) <= tol * prev.level):
                    if self._unhelped == 0:
                        self._undo_to = prev_scale
                    self._unhelped += 1    # the last step changed nothing
                    if self._unhelped == cfg.respond_steps:
                        # light that clips at any exposure: the steps that changed nothing
                        # only darkened the stripe; back to the scale before them, and hold
                        self.scale = self._undo_to
                        return self.scale
                else:
                    self._unhelped = 0
            if self._unhelped < cfg.respond_steps:
                self.scale = max(cfg.min_scale, self.scale * cfg.step_down)
            return self.scale
        self._down_from, self._unhelped = None, 0
        if stats.level < cfg.level_low and stats.near_clip <= cfg.clip_low:
            self._quiet += 1
            if self._quiet > cfg.hold_frames:
                self.scale = min(cfg.max_scale, self.scale * cfg.step_up)
        else:
            self._quiet = 0
        return self.scale
