"""The EGM link's safety policy as plain functions and small value classes (issues 6 and 25):
no sockets, no threads, no clock read; every decision takes the values it rests on (poses,
limits, time stamps, the configuration) and returns the decision, so each is tested without a
link (``tests/test_egm_policy.py``). :class:`~torchseam.robot.egm.link.EgmLink` keeps the state
and the transport and asks these functions what to do.

What may be commanded:

- :func:`check_measurement`: a measurement as the tracker hands it over (shape, NaN / inf,
  unit quaternion, ``safety.max_correction_mm``, age); :func:`check_age`: its age against
  ``safety.max_age_ms`` (and not from the future); :func:`check_gate`: the reachability gate's
  answer (a gate that raises refuses, it never opens).
- :func:`check_pose_step` / :func:`check_correction_step`: the step from the previous reply
  (``safety.max_step_mm`` / ``max_step_deg``) and, in pose mode, the lead over the fed-back TCP
  (``safety.max_lead_mm``); :func:`within_step` / :func:`reply_step`: the last check of every
  reply before it goes on the wire.

What a reply commands:

- :func:`hold_cause`: whether this cycle holds and why (``new_session``,
  ``controller_silence``, ``no_measurement``, ``watchdog``), before the measurement is checked;
  :func:`controller_silent`: whether the controller's silence has outlasted the watchdog.
- :func:`hold_pose`: a hold commands the last accepted pose; before any, the fed-back pose of
  the datagram that started the session (it passed every check of a session start), never the
  pose of the datagram being answered. :func:`pose_command` / :func:`correction_command`: what
  a pose / pathcorr reply carries, the measurement or the hold.

Whom to believe: nothing in an ``EgmRobot`` is authenticated: anyone who can put a datagram on
the wire with the controller's address and port can replay an old one or forge a new one. The
policy therefore trusts a datagram's *content* only as far as the link's own state backs it:

- :func:`controller_port`: a datagram from anything but the controller's address (and, once
  locked, its port) is foreign.
- :class:`PortTracker`: a controller that restarted on a new source port of its host is
  believed, as a new session, only after ``confirm`` consistent datagrams, each after the
  session fell silent for ``silence_s``, none with a clock the session has shown.
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
- :func:`feedback_clock_us` / :func:`feedback_pose`: the fields of an ``EgmRobot`` the session
  rests on, validated.
"""

from __future__ import annotations

import ipaddress
import math
import statistics
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from torchseam.core.transforms import quat_angle_deg as quat_angle_deg  # (re-exported)
from torchseam.robot.egm.config import EgmSafety

U32 = 0xFFFFFFFF
_HALF = 1 << 31
QUAT_TOL = 1e-3  # |q| may differ from 1 by this much (float32 sources, rounding)
_STEP_TOL = 1 + 1e-9  # the reply check's slack over max_step: a command passed the same check

#: ``gate(position_mm (3,), quaternion_wxyz (4,)) -> (ok, reason)``: may the TCP go there?
Gate = Callable[[np.ndarray, np.ndarray], "tuple[bool, str]"]
Pose = tuple[np.ndarray, np.ndarray]

#: Hold causes decided before a measurement is checked (:func:`hold_cause`); a measurement
#: that fails its checks makes the cycle a ``refused`` hold.
HOLD_NEW_SESSION = "new_session"
HOLD_SILENCE = "controller_silence"
HOLD_NO_MEASUREMENT = "no_measurement"
HOLD_WATCHDOG = "watchdog"
HOLD_REFUSED = "refused"


@dataclass(frozen=True)
class Verdict:
    """Outcome of a safety check: ``reason`` is a stable key, ``detail`` says it in words."""

    ok: bool
    reason: str = ""
    detail: str = ""


ACCEPTED = Verdict(True)

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

    def shown_clock(self, clock_us: int) -> bool:
        """Whether ``clock_us`` lies in the span of controller clocks this session has shown: a
        datagram with it belongs to this session (sent again, when it is not the newest)."""
        return self.seq is not None and self._clock_lo <= clock_us <= self._clock_hi

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


class PortTracker:
    """Decides whether the controller came back on another source port of its host.

    A controller that restarts (RobotWare opens its UDP socket again) may send from a new
    source port; until then the link takes the controller's datagrams from one port only. A
    stream from another port of the controller's host is followed here, each port by a
    :class:`SequenceTracker` of its own, and believed as the controller (``new_session``,
    reason ``new_port``) only when

    - the session has been silent for ``silence_s`` before each of its datagrams (a live
      controller keeps its port: while the session talks, nothing from another port is even
      parsed, see :meth:`admits`);
    - ``confirm`` of its datagrams were consistent (accepted in order by its tracker:
      sequence numbers and clocks advancing);
    - none of them carries a controller clock the session has shown (``replayed``: an old
      datagram of the session sent again from another port).

    Until then each is dropped as ``unconfirmed_port`` (or its tracker's own reason). At most
    ``max_candidates`` ports are followed at once (the stalest is forgotten). Datagrams from
    any other host never come here: they are foreign.
    """

    def __init__(self, *, reorder_window: int, max_gap: int, min_period_s: float, confirm: int,
                 silence_s: float, max_candidates: int = 4) -> None:
        self._make = lambda: SequenceTracker(
            reorder_window=reorder_window, max_gap=max_gap, min_period_s=min_period_s,
            confirm=confirm, silence_s=silence_s)
        self._make()  # refuses settings that would trust one datagram
        self.confirm = int(confirm)
        self.silence_s = float(silence_s)
        self.max_candidates = max(1, int(max_candidates))
        # port -> (its stream's tracker, consistent datagrams so far)
        self._ports: dict[int, list[Any]] = {}

    def admits(self, session: SequenceTracker, at: float) -> bool:
        """May a datagram from another port of the controller's host arriving at ``at`` be
        looked at (parsed) at all? Only once a session exists and has been silent for
        ``silence_s``: a controller that talks on is not elsewhere."""
        return session.started and at - session.last_at >= self.silence_s

    def decide(self, session: SequenceTracker, port: int, seq: int, clock_us: int,
               at: float) -> SeqDecision:
        """Decide on one datagram from ``port`` (the session's stream is ``session``);
        ``new_session`` / ``new_port``: take :meth:`confirmed` as the session's tracker."""
        if not self.admits(session, at):
            return SeqDecision(DROP, "unconfirmed_port")
        if session.shown_clock(clock_us):
            return SeqDecision(DROP, "replayed")
        entry = self._ports.get(port)
        if entry is None:
            if len(self._ports) >= self.max_candidates:
                stalest = min(self._ports, key=lambda p: self._ports[p][0].last_at)
                del self._ports[stalest]
            entry = self._ports[port] = [self._make(), 0]
        tracker, _ = entry
        d = tracker.decide(seq, clock_us, at)
        if d.action == DROP:
            return d
        entry[1] = 1 if d.action == NEW_SESSION else entry[1] + 1  # a restart counts afresh
        if entry[1] < self.confirm:
            return SeqDecision(DROP, "unconfirmed_port")
        return SeqDecision(NEW_SESSION, "new_port")

    def confirmed(self, port: int) -> SequenceTracker:
        """The tracker of ``port``'s stream, confirmed: the session's from now on (every other
        candidate is forgotten)."""
        tracker = self._ports[port][0]
        self._ports.clear()
        return tracker

    def clear(self) -> None:
        """The session spoke again: whatever claimed to be it elsewhere was not."""
        self._ports.clear()

    @property
    def ports(self) -> list[int]:
        """The ports followed now."""
        return list(self._ports)


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
    if not abs(n - 1.0) <= QUAT_TOL:
        return None, "bad_feedback_pose"
    return (np.array([fb.pos.x, fb.pos.y, fb.pos.z]), q / n), ""


# --------------------------------------------------------------------------- senders

def controller_port(sender: Any, controller_host: str, locked_port: int | None) -> int | None:
    """The port of ``sender`` (``(host, port, ...)``) when it is the controller: its host is
    ``controller_host`` and, once the session has locked onto a port (``locked_port``), it
    sends from that port; ``None`` for anything foreign, a malformed address included."""
    try:
        host, port = str(sender[0]), int(sender[1])
        if ipaddress.ip_address(host) != ipaddress.ip_address(controller_host):
            return None
    except (ValueError, TypeError, IndexError):
        return None
    if locked_port is not None and port != locked_port:
        return None
    return port


# --------------------------------------------------------------------------- measurements

def check_age(measured_at: float, now: float, max_age_ms: float) -> Verdict:
    """A measurement taken at ``measured_at`` may be used at ``now`` (seconds, one clock): at
    most ``max_age_ms`` old, and not more than 1 ms in the future (a clock mix-up)."""
    age_ms = (now - measured_at) * 1e3
    if age_ms > max_age_ms:
        return Verdict(False, "stale", f"measurement is {age_ms:.1f} ms old > max_age_ms "
                       f"{max_age_ms}")
    if age_ms < -1.0:  # a clock mix-up, not a measurement from the future
        return Verdict(False, "future_timestamp",
                       f"measurement time lies {-age_ms:.1f} ms in the future")
    return ACCEPTED


def check_measurement(vec: np.ndarray, quat: np.ndarray | None, measured_at: float, now: float,
                      safety: EgmSafety, mode: str) -> Verdict:
    """The checks a measurement passes before it is stored: 3 position (or offset) values and,
    for a pose, 4 quaternion values, all finite; a unit quaternion (within ``QUAT_TOL``); in
    ``pathcorr`` mode an offset (``quat`` None) no longer than ``max_correction_mm``; then
    :func:`check_age`."""
    if vec.shape != (3,) or (quat is not None and quat.shape != (4,)):
        return Verdict(False, "bad_shape", f"expected 3 position and 4 quaternion values, "
                       f"got {vec.shape} and {None if quat is None else quat.shape}")
    if not (np.isfinite(vec).all() and (quat is None or np.isfinite(quat).all())
            and math.isfinite(measured_at)):
        return Verdict(False, "non_finite", f"NaN or inf in {vec}, {quat}, t={measured_at}")
    if quat is not None and abs(float(np.linalg.norm(quat)) - 1.0) > QUAT_TOL:
        return Verdict(False, "bad_quaternion",
                       f"quaternion norm {np.linalg.norm(quat):.6f} is not 1")
    if mode == "pathcorr" and quat is None:
        norm = float(np.linalg.norm(vec))
        if norm > safety.max_correction_mm:
            return Verdict(False, "correction_too_large",
                           f"correction {norm:.3f} mm > max_correction_mm "
                           f"{safety.max_correction_mm}")
    return check_age(measured_at, now, safety.max_age_ms)


def check_gate(gate: Gate | None, position: np.ndarray, quat: np.ndarray) -> Verdict:
    """The reachability gate's verdict on a pose (no gate: accepted). The gate gets copies; a
    gate that raises refuses (``gate_error``): a failing gate never opens."""
    if gate is None:
        return ACCEPTED
    try:
        ok, why = gate(position.copy(), quat.copy())
    except Exception as e:  # noqa: BLE001 - a failing gate refuses; it never opens
        return Verdict(False, "gate_error", f"reachability gate raised {e!r}")
    if not ok:
        return Verdict(False, "gate", f"unreachable: {why}")
    return ACCEPTED


def check_pose_step(target: Pose, reference: Pose, fed_back_mm: np.ndarray,
                    safety: EgmSafety) -> Verdict:
    """Pose mode: may ``target`` be commanded next? Within ``max_step_mm`` and
    ``max_step_deg`` of ``reference`` (the last reply, or the session's start pose: see
    :func:`hold_pose`), and within ``max_lead_mm`` of the fed-back TCP position
    ``fed_back_mm``, which comes from the wire and so may only ever refuse."""
    (p, q), (ref_p, ref_q) = target, reference
    step = float(np.linalg.norm(p - ref_p))
    if step > safety.max_step_mm:
        return Verdict(False, "step_too_large",
                       f"target moves {step:.3f} mm > max_step_mm {safety.max_step_mm}")
    turn = quat_angle_deg(q, ref_q)
    if turn > safety.max_step_deg:
        return Verdict(False, "rotation_step_too_large",
                       f"target turns {turn:.3f} deg > max_step_deg {safety.max_step_deg}")
    lead = float(np.linalg.norm(p - fed_back_mm))
    if lead > safety.max_lead_mm:
        return Verdict(False, "too_far_from_robot",
                       f"target is {lead:.3f} mm from the robot > max_lead_mm "
                       f"{safety.max_lead_mm}")
    return ACCEPTED


def check_correction_step(offset: np.ndarray, last_sent: np.ndarray | None,
                          safety: EgmSafety) -> Verdict:
    """Pathcorr mode: may ``offset`` be commanded next? Within ``max_step_mm`` of the last
    offset sent in the session (of a zero offset before the first)."""
    ref = last_sent if last_sent is not None else np.zeros(3)
    step = float(np.linalg.norm(offset - ref))
    if step > safety.max_step_mm:
        return Verdict(False, "step_too_large",
                       f"correction changes by {step:.3f} mm > max_step_mm {safety.max_step_mm}")
    return ACCEPTED


# --------------------------------------------------------------------------- holds

def controller_silent(last_rx: float | None, now: float, watchdog_ms: float) -> bool:
    """Has the controller, last heard at ``last_rx`` (seconds; None: never), been silent at
    ``now`` for longer than ``watchdog_ms``?"""
    return last_rx is not None and (now - last_rx) * 1e3 > watchdog_ms


def hold_cause(*, new_session: bool, resync: bool, arrived_at: float | None, now: float,
               watchdog_ms: float) -> str:
    """Why this reply cycle holds before any measurement is checked, or ``""`` (check the
    measurement and command it): a restarted controller session holds on its start pose
    (``new_session``), the first reply after a controller silence holds (``controller_silence``),
    no measurement yet (``no_measurement``, ``arrived_at`` None), or the newest arrived longer
    than ``watchdog_ms`` before ``now`` (``watchdog``)."""
    if new_session:
        return HOLD_NEW_SESSION
    if resync:
        return HOLD_SILENCE
    if arrived_at is None:
        return HOLD_NO_MEASUREMENT
    if (now - arrived_at) * 1e3 > watchdog_ms:
        return HOLD_WATCHDOG
    return ""


# --------------------------------------------------------------------------- replies

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


def reply_step(prev_vec: np.ndarray, vec: np.ndarray, prev_quat: np.ndarray | None = None,
               quat: np.ndarray | None = None) -> tuple[float, float]:
    """Distance (mm) and, with both quaternions, rotation (deg) from one reply to the next."""
    mm = float(np.linalg.norm(np.asarray(vec, float) - np.asarray(prev_vec, float)))
    deg = 0.0 if prev_quat is None or quat is None else quat_angle_deg(prev_quat, quat)
    return mm, deg


def within_step(last_vec: np.ndarray | None, last_quat: np.ndarray | None, vec: np.ndarray,
                quat: np.ndarray | None, safety: EgmSafety) -> bool:
    """Is a reply ``(vec, quat)`` within ``max_step_mm`` / ``max_step_deg`` of the previous
    reply ``(last_vec, last_quat)`` (``last_vec`` None: none yet in the session, anything is;
    a quaternion None: position only)? The last check before the wire; a command already
    passed the same check against the same reference."""
    if last_vec is None:
        return True
    mm, deg = reply_step(last_vec, vec, last_quat, quat)
    return mm <= safety.max_step_mm * _STEP_TOL and deg <= safety.max_step_deg * _STEP_TOL


def pose_command(target: Pose | None, last_sent: Pose | None, session_start: Pose | None,
                 safety: EgmSafety) -> Pose:
    """What a pose-mode reply commands: ``target`` (an accepted measurement; ``None`` on a
    hold) when it is within a step of ``last_sent``, else the hold pose (:func:`hold_pose`)."""
    if target is not None:
        last_vec, last_quat = last_sent if last_sent is not None else (None, None)
        if within_step(last_vec, last_quat, target[0], target[1], safety):
            return target
    return hold_pose(last_sent, session_start)


def reply_age_ms(measured_at: float, now: float) -> int:
    """``EgmPathCorr.age`` of a measurement sent at ``now``: whole ms, 0..2^32-1."""
    return min(max(0, int(round((now - measured_at) * 1e3))), U32)


def correction_command(offset: np.ndarray | None, measured_at: float, now: float,
                       last_sent: np.ndarray | None, safety: EgmSafety) -> tuple[np.ndarray, int]:
    """What a pathcorr reply commands, ``(offset mm, age ms)``: ``offset`` (an accepted
    measurement taken at ``measured_at``) when it is within a step of ``last_sent``, else the
    hold: ``last_sent`` again (a zero offset before the first) with age 0, since a hold is a
    command, not a measurement."""
    if offset is not None and within_step(last_sent, None, offset, None, safety):
        return offset, reply_age_ms(measured_at, now)
    return (last_sent if last_sent is not None else np.zeros(3)), 0


__all__ = ["ACCEPT", "ACCEPTED", "DROP", "HOLD_NEW_SESSION", "HOLD_NO_MEASUREMENT",
           "HOLD_REFUSED", "HOLD_SILENCE", "HOLD_WATCHDOG", "NEW_SESSION", "QUAT_TOL", "Gate",
           "Pose", "PortTracker", "SeqDecision", "SequenceTracker", "Verdict", "check_age",
           "check_correction_step", "check_gate", "check_measurement", "check_pose_step",
           "controller_port", "controller_silent", "correction_command", "feedback_clock_us",
           "feedback_pose", "hold_cause", "hold_pose", "pose_command", "quat_angle_deg",
           "reply_age_ms", "reply_step", "within_step"]
