"""Weld planning (METHOD.md section 6): six segments, look-ahead buffer, IPI step control.

* The closed seam is welded in six segments of 60 degrees of branch angle. The torch welds one
  segment while the part is still, then the positioner turns the part 60 degrees about the
  branch axis, so every segment is welded in the same, comfortable, part of the workspace.
* The stripe runs ``look_ahead_mm`` ahead of the torch: located seam points wait in a bounded
  buffer until the torch gets there.
* IPI (eq. 30): from the current point cp towards the located point np the next commanded point
  is ip = cp + d' l, l = (np - cp) / |np - cp|, with d' the step (2 mm).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseam.core.config import CONFIG_DIR, load_config

SEGMENTS = 6
SEGMENT_NAMES = "abcdef"
MERGE_MM = 0.1  # located points closer than this to the newest one are merged into it


@dataclass(frozen=True)
class PlanConfig:
    """Planning settings (``configs/plan.yaml``)."""

    segment_start_deg: float
    approach_mm: float
    smooth_mm: float
    buffer_points: int
    work_angle_deg: float
    travel_angle_deg: float


def load_plan_config(path: str | Path | None = None) -> PlanConfig:
    return load_config(PlanConfig, path or CONFIG_DIR / "plan.yaml")


@dataclass(frozen=True)
class Segment:
    """One welding segment: branch angles [phi_start, phi_end) and the positioner turn."""

    name: str
    index: int
    phi_start: float
    phi_end: float
    rotation_deg: float


def six_segments(start_phi: float | None = None) -> list[Segment]:
    """The six segments a..f of the ring, starting at branch angle ``start_phi`` (rad; default
    ``segment_start_deg`` of ``configs/plan.yaml``).

    Segment k is welded with the part turned by ``-60 k`` degrees, which brings it to where
    segment a was.
    """
    if start_phi is None:
        start_phi = float(np.radians(load_plan_config().segment_start_deg))
    step = 2 * np.pi / SEGMENTS
    return [Segment(SEGMENT_NAMES[k], k, start_phi + k * step, start_phi + (k + 1) * step,
                    -60.0 * k) for k in range(SEGMENTS)]


def ipi_step(cp: np.ndarray, np_: np.ndarray, step_mm: float) -> np.ndarray:
    """eq. 30: the next commanded point from cp (3,) towards np (3,), ``step_mm`` away.

    If np is closer than the step, np itself (never overshoot a located point).
    """
    d = np_ - cp
    dist = float(np.linalg.norm(d))
    if dist <= step_mm or dist == 0.0:
        return np_.copy()
    return cp + step_mm * d / dist


@dataclass
class Located:
    """A located seam point waiting in the buffer (robot base, mm)."""

    s_mm: float          # arc length along the located path
    p: np.ndarray        # (3,) weld point
    q: np.ndarray        # (2, 3) points on the two stripe arms (NaN when ECAL found none)
    t_s: float           # time of the frame that saw it
    n: int = 1           # measurements averaged into it


class LookAheadBuffer:
    """Bounded FIFO of located seam points between the stripe and the torch.

    The stripe runs ahead of the torch, so when the torch reaches a located point the buffer
    holds located points on both sides of it. That is used for the commanded point, a local
    quadratic fit of the located points within ``smooth_mm`` of it, which averages the
    measurement noise without lag; for the seam tangent of the torch frame
    (:func:`~torchseam.geometry.torch_frame.torch_frame`), that fit's derivative, centred on
    the point instead of trailing it; and for the arm directions, averaged over the same points.

    Example:
        >>> buf = LookAheadBuffer(maxlen=100)
        >>> for x in range(0, 30):
        ...     buf.push(np.array([float(x), 0, 0]), np.full((2, 3), np.nan), t_s=x / 25)
        >>> ip, tangent, q = buf.next_command(np.array([0.0, 0, 0]), step_mm=2.0)
        >>> ip.round(6).tolist(), tangent.round(6).tolist()
        ([2.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    """

    def __init__(self, maxlen: int = 2048, smooth_mm: float = 3.0) -> None:
        self.points: deque[Located] = deque(maxlen=maxlen)
        self.smooth_mm = smooth_mm
        self.dropped = 0  # points pushed out by a full buffer (reported, never silent)

    def __len__(self) -> int:
        return len(self.points)

    def push(self, p: np.ndarray, q: np.ndarray, t_s: float) -> None:
        """Add a located point (``q``: (2, 3) arm points). A point within ``MERGE_MM`` of the
        newest one (the sensor standing still) is averaged into it instead of appended."""
        p = np.asarray(p, float)
        if self.points and np.linalg.norm(p - self.points[-1].p) < MERGE_MM:
            last = self.points[-1]
            n = last.n + 1
            last.p = last.p + (p - last.p) / n
            q = np.asarray(q, float)
            if np.all(np.isfinite(q)):
                last.q = q if not np.all(np.isfinite(last.q)) else last.q + (q - last.q) / n
            last.n, last.t_s = n, t_s
            return
        s = 0.0 if not self.points else self.points[-1].s_mm + float(
            np.linalg.norm(p - self.points[-1].p))
        if len(self.points) == self.points.maxlen:
            self.dropped += 1
        self.points.append(Located(s, p, np.asarray(q, float), t_s))

    def ahead_mm(self, cp: np.ndarray) -> float:
        """Distance from cp to the newest located point (what the stripe has seen ahead)."""
        return float(np.linalg.norm(self.points[-1].p - cp)) if self.points else 0.0

    def fit(self, k: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Smoothed point, unit tangent and mean unit arm directions (2, 3) at buffered point
        ``k``: a local quadratic over the points within ``smooth_mm`` of it, parameterised by
        frame time; the median arm directions over the same points (NaN if none had arms). The
        tangent is None when fewer than 4 points support the fit (the seam seen at one spot
        only, e.g. before the robot moves)."""
        s = np.array([loc.s_mm for loc in self.points])
        sel = np.nonzero(np.abs(s - s[k]) <= self.smooth_mm)[0]
        arms = np.stack([self.points[i].q - self.points[i].p for i in sel])   # (n, 2, 3)
        arms = arms / np.linalg.norm(arms, axis=2, keepdims=True)
        good = np.all(np.isfinite(arms), axis=(1, 2))
        # the median, not the mean: one ECAL crossing taken on a spatter streak must not tilt
        # the torch
        mean = np.median(arms[good], axis=0) if good.any() else np.full((2, 3), np.nan)
        mean = mean / np.linalg.norm(mean, axis=1, keepdims=True)
        if len(sel) < 4:
            return self.points[k].p, None, mean
        # fit in frame time, not in the (noisy) arc length: points arrive at a steady rate
        x = np.array([self.points[i].t_s for i in sel]) - self.points[k].t_s
        P = np.stack([self.points[i].p for i in sel])
        A = np.stack([np.ones_like(x), x, x * x], axis=1)
        coef = np.linalg.lstsq(A, P, rcond=None)[0]  # (3, 3): rows c0, c1, c2
        return coef[0], coef[1] / np.linalg.norm(coef[1]), mean

    def next_command(self, cp: np.ndarray, step_mm: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """IPI step from cp: ``(ip (3,), tangent (3,) or None, arm_dirs (2, 3))`` or None when
        nothing is located a step ahead yet (tangent None: too few points around np to fit).

        np is the first buffered point at least one step from cp (smoothed); points the torch
        has passed are dropped. ``arm_dirs`` are the smoothed unit arm directions at np, for the
        torch frame: ``torch_frame(ip, ip + arm_dirs[0], ip + arm_dirs[1], tangent=tangent)``.
        """
        while len(self.points) > 1 and np.linalg.norm(self.points[1].p - cp) < step_mm and (
                np.linalg.norm(self.points[0].p - cp) < step_mm):
            self.points.popleft()
        target = next((k for k, loc in enumerate(self.points)
                       if np.linalg.norm(loc.p - cp) >= step_mm), None)
        if target is None:
            return None
        p_np, tangent, arm_dirs = self.fit(target)
        return ipi_step(cp, p_np, step_mm), tangent, arm_dirs
