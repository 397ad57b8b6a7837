"""The EGM link's safety policy, free of sockets (issue 25): which ``EgmRobot`` belongs to the
controller's session, and what a hold commands.

Nothing in an ``EgmRobot`` is authenticated: anyone who can put a datagram on the wire with the
controller's address and port can replay an old one or forge a new one. The policy therefore
trusts a datagram's *content* only as far as the link's own state backs it:

- :class:`SequenceTracker` follows the controller's stream by ``header.seqno`` and the
  controller's clock ``feedBack.time``, and tells the link for each datagram whether it
  continues the session (``accept``), starts a new one (``new_session``), or is dropped, with
  the reason. A jump ahead is taken at once only as far as the link's own clock explains it (one
  controller period per sequence number, ``max_gap`` more for free); further ahead it is a
  *candidate* stream. A datagram behind the newest is a reordered one (``out_of_order``), an old
  one of this session replayed (``replayed``: its clock lies inside the span this session has
  shown), or, with a clock outside that span, the first of a possible restart (a candidate). A
  candidate becomes the stream only after ``confirm`` consistent datagrams (sequence numbers and
  clocks both advancing) while the current session stays silent for ``silence_s``: a genuine
  stream that keeps talking discards every candidate, so no single datagram, and no forged
  stream interleaved with the genuine one, can take the session over or block it.
- :func:`hold_pose`: a hold commands the last accepted pose; before any, the fed-back pose of
  the datagram that started the session (it passed every check of a session start), never the
  pose of the datagram being answered.
- :func:`reply_step`: how far one reply is from the previous (mm, degrees), for the link's final
  check that every reply stays within ``safety.max_step_mm`` / ``max_step_deg``.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

U32 = 0xFFFFFFFF
_HALF = 1 << 31
_QUAT_TOL = 1e-3  # |q| may differ from 1 by this much (float32 sources, rounding)

ACCEPT = "accept"
DROP = "drop"
NEW_SESSION = "new_session"


class SeqDecision(NamedTuple):
    """What to do with one ``EgmRobot``.

    ``action``: ``accept`` (continues the session), ``new_session`` (starts one: the first
    datagram of the link, or a confirmed restart of the controller) or ``drop``. ``reason``:
    for ``drop`` the drop reason; for ``accept`` ``""`` or ``"jump"`` (a confirmed far jump
    ahead); for ``new_session`` ``"first"`` or ``"restart"``. ``missing``: sequence numbers the
    accepted datagram skipped.
    """

    action: str
    reason: str = ""
    missing: int = 0


@dataclass
class _Candidate:
    kind: str         # "jump" (far ahead) or "restart" (behind, clock outside the session's)
    last_seq: int
    last_clock: int   # us
    last_at: float    # link clock s
    count: int = 1


def _ahead(a: int, b: int) -> int:
    """``a - b`` modulo 2^32 (seqno arithmetic)."""
    return (a - b) & U32


class SequenceTracker:
    """Decides accept / drop / new session from ``(seqno, controller clock, arrival time)``.

    Args:
        reorder_window: a datagram up to this many sequence numbers behind the newest, with a
            clock inside the session's span, is a reordered one (``out_of_order``); further
            behind it is ``replayed``.
        max_gap: a sequence number up to this far ahead of the newest is taken without any
            time evidence (1: only the next one).
        min_period_s: the controller's shortest cycle (EGM: 4 ms).
        confirm: consistent datagrams a candidate stream (far jump or restart) needs.
        silence_s: how long the current session must have said nothing before a candidate can
            take over (a controller that restarts has stopped first).
        max_candidates: candidate streams tracked at once (the oldest is forgotten).
        history: accepted datagrams the time evidence rests on.

    Time evidence: each of the last ``history`` accepted datagrams says which sequence number
    the controller should have reached by now (its own, plus one per controller period since it
    arrived; the period is the median spacing of the stream, never below ``min_period_s``).
    A jump ahead beyond ``max_gap`` is taken when it lies at most ``max_gap`` past the *median*
    of those: after lost datagrams the genuine stream is right on it, while a few forged
    datagrams among the accepted ones (early, late, high or low) move the median nowhere.

    ``at`` (arrival time, seconds) is on any clock of the caller's as long as it is one clock;
    the controller clock ``clock_us`` is ``feedBack.time`` in microseconds.
    """

    def __init__(self, *, reorder_window: int, max_gap: int, min_period_s: float, confirm: int,
                 silence_s: float, max_candidates: int = 4, history: int = 15) -> None:
        if max_gap < 1 or confirm < 2 or not min_period_s > 0.0 or history < 1:
            raise ValueError("need max_gap >= 1, confirm >= 2, min_period_s > 0, history >= 1")
        self.reorder_window = int(reorder_window)
        self.max_gap = int(max_gap)
        self.min_period_s = float(min_period_s)
        self.confirm = int(confirm)
        self.silence_s = float(silence_s)
        self.max_candidates = int(max_candidates)
        self.seq: int | None = None        # newest accepted seqno
        self.last_at: float = 0.0          # when the session's last accepted datagram arrived
        self._u = 0                        # the newest seqno, unwrapped (no modulo 2^32)
        self._hist: deque[tuple[int, float]] = deque(maxlen=history)  # accepted (u, at)
        self._periods: deque[float] = deque(maxlen=2 * history + 1)  # s per seqno
        self._clock_lo = 0                 # span of controller clocks the session has shown
        self._clock_hi = 0
        self._candidates: list[_Candidate] = []

    # ------------------------------------------------------------------ queries

    @property
    def started(self) -> bool:
        return self.seq is not None

    def period_s(self) -> float:
        """The controller's period as the stream shows it (median), never below the minimum."""
        if not self._periods:
            return self.min_period_s
        return max(self.min_period_s, statistics.median(self._periods))

    def expected_ahead(self, at: float) -> float:
        """How far ahead of the newest the controller's seqno should be at time ``at``: the
        median over the recent accepted datagrams of their seqno plus the periods since."""
        period = self.period_s()
        u = self._u
        ahead = sorted(ui - u + (at - ai) / period for ui, ai in self._hist)
        n = len(ahead)
        return ahead[n // 2] if n % 2 else 0.5 * (ahead[n // 2 - 1] + ahead[n // 2])

    # ------------------------------------------------------------------ the decision

    def decide(self, seq: int, clock_us: int, at: float) -> SeqDecision:
        """Decide on one datagram (``seq`` 0..2^32-1, ``clock_us`` >= 0, ``at`` seconds)."""
        seq &= U32
        if not math.isfinite(at):
            at = self.last_at
        if self.seq is None:
            self._start(seq, clock_us, at)
            return SeqDecision(NEW_SESSION, "first")
        d = _ahead(seq, self.seq)
        if d == 0:
            return SeqDecision(DROP, "duplicate")
        if d < _HALF:  # ahead of the newest
            if d <= self.max_gap or d <= self.expected_ahead(at) + self.max_gap:
                self._advance(seq, clock_us, at, d)
                return SeqDecision(ACCEPT, "", d - 1)
            return self._candidate("jump", seq, clock_us, at, "unconfirmed_jump")
        back = _ahead(self.seq, seq)
        if self._clock_lo <= clock_us <= self._clock_hi:  # a clock this session has shown
            return SeqDecision(DROP, "out_of_order" if back <= self.reorder_window
                               else "replayed")
        return self._candidate("restart", seq, clock_us, at, "unconfirmed_session")

    def _start(self, seq: int, clock_us: int, at: float) -> None:
        self.seq, self.last_at, self._u = seq, at, 0
        self._hist.clear()
        self._hist.append((0, at))
        self._periods.clear()
        self._clock_lo = self._clock_hi = clock_us
        self._candidates.clear()

    def _advance(self, seq: int, clock_us: int, at: float, d: int) -> None:
        if at > self.last_at:
            self._periods.append((at - self.last_at) / d)
        self._u += d
        self.seq, self.last_at = seq, at
        self._hist.append((self._u, at))
        self._clock_lo = min(self._clock_lo, clock_us)
        self._clock_hi = max(self._clock_hi, clock_us)
        # the session is alive: whatever else claimed to be the controller meanwhile was not
        self._candidates.clear()

    def _candidate(self, kind: str, seq: int, clock_us: int, at: float,
                   reason: str) -> SeqDecision:
        cand = None
        for c in self._candidates:
            step = _ahead(seq, c.last_seq)
            if (c.kind == kind and 0 < step < _HALF and clock_us >= c.last_clock
                    and step <= self.max_gap + max(0.0, at - c.last_at) / self.min_period_s):
                cand = c
                break
        if cand is None:
            if len(self._candidates) >= self.max_candidates:
                self._candidates.remove(min(self._candidates, key=lambda c: c.last_at))
            self._candidates.append(_Candidate(kind, seq, clock_us, at))
            return SeqDecision(DROP, reason)
        cand.last_seq, cand.last_clock, cand.last_at = seq, clock_us, at
        cand.count += 1
        if cand.count < self.confirm or not at - self.last_at >= self.silence_s:
            return SeqDecision(DROP, reason)
        if kind == "restart":
            self._start(seq, clock_us, at)
            return SeqDecision(NEW_SESSION, "restart")
        # the same session, resumed far ahead: the time evidence starts again from here
        clock_lo, clock_hi = min(self._clock_lo, clock_us), max(self._clock_hi, clock_us)
        self._start(seq, clock_us, at)
        self._clock_lo, self._clock_hi = clock_lo, clock_hi
        return SeqDecision(ACCEPT, "jump")


# --------------------------------------------------------------------------- datagram fields

def feedback_clock_us(robot: Any) -> tuple[int | None, str]:
    """The controller clock ``feedBack.time`` in microseconds, or ``(None, reason)``:
    ``no_feedback_time`` (RobotWare before 6.07 sends none, and mixes radians and degrees in
    its feedback: refused) or ``bad_feedback_time`` (``usec`` of a million or more)."""
    if not robot.feedBack.HasField("time"):
        return None, "no_feedback_time"
    t = robot.feedBack.time
    if t.usec >= 1_000_000:
        return None, "bad_feedback_time"
    return int(t.sec) * 1_000_000 + int(t.usec), ""


def feedback_pose(robot: Any) -> tuple[tuple[np.ndarray, np.ndarray] | None, str]:
    """The fed-back TCP ``(position mm, unit quaternion w, x, y, z)`` or ``(None, reason)``:
    ``no_feedback_pose`` (no position or quaternion) or ``bad_feedback_pose`` (the quaternion
    is not unit length)."""
    fb = robot.feedBack.cartesian
    if not (robot.feedBack.HasField("cartesian") and fb.HasField("pos")
            and fb.HasField("orient")):
        return None, "no_feedback_pose"
    q = np.array([fb.orient.u0, fb.orient.u1, fb.orient.u2, fb.orient.u3])
    n = float(np.linalg.norm(q))
    if not abs(n - 1.0) <= _QUAT_TOL:
        return None, "bad_feedback_pose"
    return (np.array([fb.pos.x, fb.pos.y, fb.pos.z]), q / n), ""


# --------------------------------------------------------------------------- replies

Pose = tuple[np.ndarray, np.ndarray]


def hold_pose(reference: Pose | None, session_start: Pose | None) -> Pose:
    """The pose a hold commands: the last accepted pose (``reference``, the last reply); before
    any, the fed-back pose of the datagram that started the session, which then becomes the
    reference. Never the pose of the datagram being answered.

    Raises:
        ValueError: neither exists (the link never answers before a session started).
    """
    if reference is not None:
        return reference
    if session_start is not None:
        return session_start
    raise ValueError("no accepted pose and no session start to hold at")


def quat_angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    """Rotation angle between two unit quaternions (w, x, y, z), degrees."""
    d = min(1.0, abs(float(np.dot(q1, q2))))
    return math.degrees(2.0 * math.acos(d))


def reply_step(prev_vec: np.ndarray, vec: np.ndarray, prev_quat: np.ndarray | None = None,
               quat: np.ndarray | None = None) -> tuple[float, float]:
    """Distance (mm) and, with both quaternions, rotation (deg) from one reply to the next."""
    mm = float(np.linalg.norm(np.asarray(vec, float) - np.asarray(prev_vec, float)))
    deg = 0.0 if prev_quat is None or quat is None else quat_angle_deg(prev_quat, quat)
    return mm, deg


__all__ = ["ACCEPT", "DROP", "NEW_SESSION", "SeqDecision", "SequenceTracker",
           "feedback_clock_us", "feedback_pose", "hold_pose", "quat_angle_deg", "reply_step"]
