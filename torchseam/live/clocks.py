"""Three clocks of a weld cell, related explicitly: the PC's, the camera's and the controller's.

A frame carries its exposure time on the camera's clock; the controller's ``EgmRobot`` carries
the fed-back pose with its time on the controller's clock (``feedBack.time``); the weld runs
on the PC's monotonic clock (the EGM link's). The pose used for a frame is the fed-back pose
interpolated at the frame's exposure time, so both remote times are brought onto the PC's:

* :class:`ClockOffset` estimates ``offset = pc - remote`` online from messages stamped by the
  remote clock and received on the PC's: ``arrival_pc - stamp_remote = offset + delay``, with
  the delay at least the known one (the camera's latency from exposure to arrival, from the
  cell file; the controller's one EGM cycle from the pose's measurement to its datagram). The
  smallest ``arrival - stamp`` over a sliding window, less the known delay, is the offset:
  a message held up on its way (a busy PC, a late frame) only makes its own difference
  larger, never the estimate wrong. Where the remote stamp itself can come late (a controller
  whose cycle ran late stamps a pose that then leaves early), a low quantile of the window
  (``quantile``) replaces the minimum: a few such outliers do not move it. A remote clock
  that jumps (a controller restart, a camera reset) shows as differences that no longer fit
  the window: the estimator starts again.
* :class:`PoseHistory` keeps the fed-back torch poses with their PC times and interpolates
  one at any time between two of them. A time with no fed-back pose on both sides within
  ``max_gap_s`` gives None: no pose, so no measurement for that frame (never a guess).
"""

from __future__ import annotations

import collections
import math
import threading

import numpy as np

from torchseam.core.transforms import matrix_to_quat, pose_matrix, slerp


class ClockOffset:
    """Online estimate of ``pc - remote`` (seconds) from stamped messages.

    Args:
        known_delay_s: the smallest delay from the remote stamp to the PC's arrival time
            (camera: the latency from the cell file; controller: one EGM cycle).
        window: messages the minimum is taken over (a few seconds of messages).
        jump_s: a difference this much below the estimate, or the estimate this much below
            every difference of the window, is a jump of the remote clock: start again.

    Example:
        >>> off = ClockOffset(known_delay_s=0.020)
        >>> off.add(remote_s=5.000, arrival_s=105.021)
        >>> round(off.to_pc(5.000), 3)
        100.001
    """

    def __init__(self, known_delay_s: float = 0.0, window: int = 500, jump_s: float = 0.5,
                 quantile: float = 0.0) -> None:
        if not math.isfinite(known_delay_s) or known_delay_s < 0:
            raise ValueError(f"known_delay_s must be a finite delay >= 0, got {known_delay_s}")
        if not 0.0 <= quantile < 0.5:
            raise ValueError(f"quantile must be in [0, 0.5), got {quantile}")
        self.known_delay_s = float(known_delay_s)
        self.quantile = float(quantile)
        self._q_value: float | None = None
        self.jump_s = float(jump_s)
        self._diffs: collections.deque[float] = collections.deque(maxlen=max(1, int(window)))
        self._min: float | None = None
        self.resets = 0          # times the remote clock jumped and the estimate started again
        self._lock = threading.Lock()

    def add(self, remote_s: float, arrival_s: float) -> None:
        """One message stamped ``remote_s`` on the remote clock, arriving at ``arrival_s``."""
        d = float(arrival_s) - float(remote_s)
        if not math.isfinite(d):
            return
        with self._lock:
            m = self._min
            if m is not None and (d < m - self.jump_s or d > m + self.jump_s * 4 and all(
                    x > m + self.jump_s for x in list(self._diffs)[-8:])):
                # the remote clock jumped (backwards: d far below; forwards: the last
                # messages all far above the minimum): the old window describes another clock
                self._diffs.clear()
                self._min = m = None
                self._q_value = None
                self.resets += 1
            full = len(self._diffs) == self._diffs.maxlen
            dropped = self._diffs[0] if full else None
            self._diffs.append(d)
            if m is None or d < m:
                self._min = d
            elif dropped is not None and dropped <= m:
                self._min = min(self._diffs)
            if self.quantile > 0.0 and (len(self._diffs) < 50 or len(self._diffs) % 25 == 0):
                self._q_value = float(np.quantile(np.fromiter(self._diffs, float),
                                                  self.quantile))

    @property
    def ready(self) -> bool:
        """Whether any message has been seen."""
        return self._min is not None

    @property
    def offset_s(self) -> float:
        """``pc - remote`` (s); NaN before the first message."""
        m = self._min if self.quantile == 0.0 or self._q_value is None else self._q_value
        return float("nan") if m is None else m - self.known_delay_s

    def to_pc(self, remote_s: float) -> float:
        """A remote time on the PC's clock (NaN before the first message)."""
        return float(remote_s) + self.offset_s

    def to_remote(self, pc_s: float) -> float:
        """A PC time on the remote clock (NaN before the first message)."""
        return float(pc_s) - self.offset_s


class PoseHistory:
    """Fed-back torch poses ``(t_pc, T (4, 4))`` in time order, interpolated at any time.

    Args:
        maxlen: poses kept (250 Hz: 1 000 is 4 s).
        max_gap_s: interpolate only between two poses at most this far apart; a time outside
            the history or inside a larger gap has no pose.

    Thread-safe: the EGM link's thread adds, the weld's thread reads.
    """

    def __init__(self, maxlen: int = 1000, max_gap_s: float = 0.02) -> None:
        self.max_gap_s = float(max_gap_s)
        self._t: collections.deque[float] = collections.deque(maxlen=maxlen)
        self._T: collections.deque[np.ndarray] = collections.deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, t_pc: float, T: np.ndarray) -> None:
        """A fed-back pose at ``t_pc``; one not after the newest is ignored (reordered)."""
        with self._lock:
            if self._t and t_pc <= self._t[-1]:
                return
            self._t.append(float(t_pc))
            self._T.append(np.array(T, dtype=float))

    def clear(self) -> None:
        """Forget every pose (the controller's clock jumped: its times are another clock's)."""
        with self._lock:
            self._t.clear()
            self._T.clear()

    @property
    def newest(self) -> tuple[float, np.ndarray] | None:
        """The newest ``(t_pc, T)``, or None."""
        with self._lock:
            if not self._t:
                return None
            return self._t[-1], self._T[-1].copy()

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """Every pose held: times (N,) and poses (N, 4, 4)."""
        with self._lock:
            return np.fromiter(self._t, float, len(self._t)), np.array(list(self._T)).reshape(
                -1, 4, 4)

    def positions_at(self, t_pc: np.ndarray) -> np.ndarray:
        """(M, 3) positions at times ``t_pc`` (M,), linear between the poses around each;
        NaN outside the history or inside a gap over ``max_gap_s`` (vectorised :meth:`at`)."""
        t, T = self.snapshot()
        q = np.asarray(t_pc, float)
        out = np.full((len(q), 3), np.nan)
        if len(t) < 2:
            return out
        i = np.clip(np.searchsorted(t, q, side="right"), 1, len(t) - 1)
        t0, t1 = t[i - 1], t[i]
        ok = (q >= t[0]) & (q <= t[-1]) & (t1 - t0 <= self.max_gap_s)
        w = np.where(t1 > t0, (q - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)[:, None]
        P = (1 - w) * T[i - 1, :3, 3] + w * T[i, :3, 3]
        out[ok] = P[ok]
        return out

    def nearest(self, t_pc: float, within_s: float) -> np.ndarray | None:
        """The held pose nearest to ``t_pc`` if it is at most ``within_s`` away, else None."""
        with self._lock:
            n = len(self._t)
            if n == 0:
                return None
            ts = np.fromiter(self._t, float, n)
            i = int(np.argmin(np.abs(ts - t_pc)))
            if abs(ts[i] - t_pc) > within_s:
                return None
            return self._T[i].copy()

    def at(self, t_pc: float) -> np.ndarray | None:
        """The pose (4, 4) at ``t_pc``: interpolated between the fed-back poses around it
        (position linear, orientation slerp), or None when there is none on one side or the
        two are more than ``max_gap_s`` apart."""
        with self._lock:
            n = len(self._t)
            if n == 0 or not (self._t[0] <= t_pc <= self._t[-1]):
                return None
            ts = np.fromiter(self._t, float, n)
            i = int(np.searchsorted(ts, t_pc, side="right"))
            if i >= n:      # exactly the newest
                return self._T[-1].copy()
            t0, t1 = ts[i - 1], ts[i]
            if t1 - t0 > self.max_gap_s:
                return None
            A, B = self._T[i - 1], self._T[i]
        w = (t_pc - t0) / (t1 - t0) if t1 > t0 else 0.0
        q = slerp(matrix_to_quat(A[:3, :3]), matrix_to_quat(B[:3, :3]), w)
        return pose_matrix((1 - w) * A[:3, 3] + w * B[:3, 3], q)
