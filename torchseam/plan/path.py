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

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

SEGMENTS = 6
SEGMENT_NAMES = "abcdef"


@dataclass(frozen=True)
class Segment:
    """One welding segment: branch angles [phi_start, phi_end) and the positioner turn."""

    name: str
    index: int
    phi_start: float
    phi_end: float
    rotation_deg: float


def six_segments(start_phi: float = 0.0) -> list[Segment]:
    """The six segments a..f of the ring, starting at branch angle ``start_phi`` (rad).

    Segment k is welded with the part turned by ``-60 k`` degrees, which brings it to where
    segment a was.
    """
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
    """A located seam point waiting in the buffer."""

    s_mm: float          # arc length along the located path
    p: np.ndarray        # (3,) mm, robot base
    R: np.ndarray        # (3, 3) torch orientation
    t_s: float           # time of the frame that saw it


class LookAheadBuffer:
    """Bounded FIFO of located seam points between the stripe and the torch.

    Example:
        >>> buf = LookAheadBuffer(maxlen=100)
        >>> for x in range(0, 30):
        ...     buf.push(np.array([float(x), 0, 0]), np.eye(3), t_s=x / 25)
        >>> ip, R = buf.next_command(np.array([0.0, 0, 0]), step_mm=2.0)
        >>> ip.tolist()
        [2.0, 0.0, 0.0]
    """

    def __init__(self, maxlen: int = 2048) -> None:
        self.points: deque[Located] = deque(maxlen=maxlen)
        self.dropped = 0  # points pushed out by a full buffer (reported, never silent)

    def __len__(self) -> int:
        return len(self.points)

    def push(self, p: np.ndarray, R: np.ndarray, t_s: float) -> None:
        s = 0.0 if not self.points else self.points[-1].s_mm + float(
            np.linalg.norm(p - self.points[-1].p))
        if len(self.points) == self.points.maxlen:
            self.dropped += 1
        self.points.append(Located(s, np.asarray(p, float), np.asarray(R, float), t_s))

    def ahead_mm(self, cp: np.ndarray) -> float:
        """Distance from cp to the newest located point (what the stripe has seen ahead)."""
        return float(np.linalg.norm(self.points[-1].p - cp)) if self.points else 0.0

    def next_command(self, cp: np.ndarray, step_mm: float
                     ) -> tuple[np.ndarray, np.ndarray] | None:
        """IPI step from cp: (ip (3,), R (3, 3)) or None when nothing is located far enough.

        np is the first buffered point at least one step from cp; points the torch has passed
        are dropped. The orientation is slerped between the buffered frames around ip.
        """
        while self.points and np.linalg.norm(self.points[0].p - cp) < step_mm and len(
                self.points) > 1 and np.linalg.norm(self.points[1].p - cp) < step_mm:
            self.points.popleft()
        target = next((k for k, loc in enumerate(self.points)
                       if np.linalg.norm(loc.p - cp) >= step_mm), None)
        if target is None:
            return None
        ip = ipi_step(cp, self.points[target].p, step_mm)
        R = self._orientation_at(ip, target)
        return ip, R

    def _orientation_at(self, ip: np.ndarray, k: int) -> np.ndarray:
        if k == 0:
            return self.points[0].R
        a, b = self.points[k - 1], self.points[k]
        seg = b.p - a.p
        L2 = float(seg @ seg)
        f = 0.0 if L2 == 0 else float(np.clip((ip - a.p) @ seg / L2, 0.0, 1.0))
        rots = Rotation.from_matrix(np.stack([a.R, b.R]))
        return Slerp([0.0, 1.0], rots)([f]).as_matrix()[0]
