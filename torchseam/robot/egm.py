"""Sensor side of ABB Externally Guided Motion (EGM) over UDP, with the safety of issues 6 and 25.

The controller sends an ``EgmRobot`` every cycle (4 ms at 250 Hz) to the sensor's address; the
link answers every valid one, to its sender, with the latest accepted command:

- ``mode: pose`` -> ``EgmSensor``: the planned TCP pose in the base frame (mm, quaternion w, x,
  y, z), for position guidance (``EGMActPose`` / ``EGMRunPose``);
- ``mode: pathcorr`` -> ``EgmSensorPathCorr``: the offset of the seam from the programmed path
  in the path (sensor tool) frame, mm, and the measurement age, ms (``EGMActMove`` /
  ``EGMMoveL``, the seam-tracking mode). EGM treats the offset as absolute: it is where the seam
  is, not a step.

The tracker feeds measurements with :meth:`EgmLink.set_target` / :meth:`EgmLink.set_correction`
from its own thread; the link thread answers the controller with the newest one that passes
every check. What is never sent (each refusal is logged with its reason and counted in
:class:`EgmStats`):

- a NaN / inf, a quaternion that is not unit length, a correction larger than
  ``safety.max_correction_mm``;
- a pose the pluggable ``gate`` refuses (the reachability gate of the live loop);
- a step larger than ``safety.max_step_mm`` (``max_step_deg`` for orientation) from the
  previous reply of the session (pose mode: before any reply, from the fed-back pose of the
  datagram that started the session; pathcorr: from a zero offset); in pose mode a target
  further than ``safety.max_lead_mm`` from the fed-back TCP;
- a measurement older than ``safety.max_age_ms`` when the reply leaves.

A refused measurement is logged and counted once (not once per 4 ms cycle it stays refused).

Instead of a refused command the link sends a *hold*; the watchdog sends holds as well when no
new measurement arrived for ``safety.watchdog_ms`` (and before the first one). A hold commands
the last accepted command again, never anything taken from the datagram it answers
(:func:`~torchseam.robot.egm_policy.hold_pose`):

- pose mode: the last sent pose (the robot finishes the last vetted step and stops there);
  before anything was sent in a session, the fed-back pose of the datagram that started the
  session, which becomes the reference of the next step;
- pathcorr mode: the last sent offset again (zero before the first), with age 0: a hold is a
  command, not a measurement. A zero offset is *not* a hold under EGM's absolute semantics:
  it would pull the torch back onto the programmed path by up to ``max_correction_mm``. The
  programmed path itself keeps running; stopping it is RAPID's job.

Every reply, hold included, is within ``max_step_mm`` / ``max_step_deg`` of the previous reply
of the session (checked once more as the reply is built).

Which datagrams belong to the controller's session is decided by
:class:`~torchseam.robot.egm_policy.SequenceTracker` from ``header.seqno``, the controller's
clock ``feedBack.time`` and the link's own clock: duplicates, reordered datagrams (behind the
newest), replays of this session (far behind, with a clock this session has already shown) are
dropped; a jump ahead is taken at once only as far as the link's clock explains it
(``link.max_gap`` more for free), further ahead only after ``link.session_confirm`` consistent
successors while the session stays silent. A new session (the controller restarted: sequence
number and clock both restarting) is recognised the same way, never from one datagram; its
first reply is a hold (``new_session``) on its own start pose (pathcorr: a zero offset). The
very first datagram of a link starts its first session.

When the controller falls silent for longer than ``safety.watchdog_ms`` the link logs it, and
answers its first ``EgmRobot`` afterwards with a hold (``controller_silence``).

Datagrams that are oversized, empty, unparseable, of the wrong type (``header.mtype`` not
``DATA``), missing a required field, non-finite, without ``header.seqno``, without
``feedBack.time`` (RobotWare before 6.07, which mixes radians and degrees: refused), from a
foreign sender, or refused by the sequence policy are counted by reason and dropped; they never
raise out of the loop. The first of each reason is logged as a warning, the rest at debug level.
Every datagram the link reads lands in exactly one counter: ``received`` or one ``dropped``
reason. Datagrams the kernel dropped because the socket's receive buffer was full (Linux
``SO_RXQ_OVFL``) are counted in ``EgmStats.kernel_dropped``.

Binding: ``network.host`` (loopback by default); a non-loopback address is logged as a warning.
``link.rt_priority`` asks for SCHED_FIFO for the serving thread. Keep the link out of a process
whose other threads hold the GIL for milliseconds (torch inference): a reply waits for it.
"""

from __future__ import annotations

import collections
import dataclasses
import errno
import ipaddress
import logging
import math
import os
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from torchseam.core.errors import TorchseamError
from torchseam.robot.egm_config import EgmConfig, load_egm_config
from torchseam.robot.egm_messages import EgmHeader, EgmRobot, EgmSensor, EgmSensorPathCorr
from torchseam.robot.egm_policy import (
    DROP,
    NEW_SESSION,
    SequenceTracker,
    feedback_clock_us,
    feedback_pose,
    hold_pose,
    quat_angle_deg,
    reply_step,
)

log = logging.getLogger("torchseam.robot.egm")

#: ``gate(position_mm (3,), quaternion_wxyz (4,)) -> (ok, reason)``: may the TCP go there?
Gate = Callable[[np.ndarray, np.ndarray], "tuple[bool, str]"]

_U32 = 0xFFFFFFFF
# Linux: kernel receive time stamps on a datagram socket (SO_TIMESTAMPNS, CLOCK_REALTIME).
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35) if sys.platform == "linux" else None
TIMESPEC = struct.Struct("@qq")
# Linux: the socket's drop counter (receive buffer full) in each datagram's ancillary data
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40) if sys.platform == "linux" else None
_U32_STRUCT = struct.Struct("@I")
_ANC_BYTES = socket.CMSG_SPACE(TIMESPEC.size) + socket.CMSG_SPACE(_U32_STRUCT.size) + 64
_QUAT_TOL = 1e-3  # |q| may differ from 1 by this much (float32 sources, rounding)
# what a drop reason means, for the first warning of each
_DROP_DETAIL = {
    "no_feedback_time": "EgmRobot without feedBack.time: RobotWare before 6.07 (which mixes "
                        "radians and degrees in its feedback) is not supported",
    "bad_feedback_time": "feedBack.time.usec is a million or more",
    "no_seqno": "EgmRobot without header.seqno: its place in the stream is unknown",
    "no_feedback_pose": "pose mode needs the fed-back TCP pose",
    "bad_feedback_pose": "the fed-back quaternion is not unit length",
    "duplicate": "the newest sequence number again",
    "out_of_order": "behind the newest sequence number (reordered)",
    "replayed": "far behind the newest sequence number, with a controller clock this session "
                "already showed: an old datagram sent again",
    "unconfirmed_jump": "further ahead than the time the stream has run explains; believed "
                        "only after consistent successors while the session is silent",
    "unconfirmed_session": "behind the newest with a clock outside the session's: a restart "
                           "is believed only after consistent successors while the session "
                           "is silent",
}


class EgmError(TorchseamError):
    """The EGM link cannot run: e.g. its UDP port is taken."""


@dataclass(frozen=True)
class Verdict:
    """Outcome of a safety check: ``reason`` is a stable key, ``detail`` says it in words."""

    ok: bool
    reason: str = ""
    detail: str = ""


ACCEPTED = Verdict(True)


# --------------------------------------------------------------------------- statistics

class LateReply(NamedTuple):
    """One late reply of the link, by where its time went (wall-clock ns / ms).

    A reply answers the newest of the ``EgmRobot`` queued when the serving thread woke (the
    older ones are superseded); it is late when it left more than ``link.late_reply_ms`` after
    the oldest of them arrived. ``wait_ms`` (that one in the kernel before the thread woke) and
    the part of ``work_ms`` not in ``cpu_ms`` are time the thread did not run: the scheduler,
    another process or the hypervisor had its CPU. ``cpu_ms`` is the link's own work (parse,
    answer, ``sendto``: the thread's CPU clock, which stops while it is off the CPU).
    """

    first_rx_ns: int  # kernel receive time of the oldest EgmRobot answered (CLOCK_REALTIME)
    rx_ns: int        # ... of the newest, the one the reply answers
    wait_ms: float    # first_rx_ns -> serving thread awake
    work_ms: float    # awake -> after ``sendto``
    cpu_ms: float     # CPU time the serving thread used in ``work_ms``


@dataclass
class EgmStats:
    """Counters of one link (all cumulative since start).

    Attributes:
        received: valid ``EgmRobot`` datagrams accepted (every datagram read is counted in
            ``received`` or in one ``dropped`` reason, never both).
        sent: replies sent.
        commands: replies that carried an accepted measurement (the rest are holds).
        holds: reply cycles answered with a hold, by cause (``no_measurement``, ``watchdog``,
            ``refused``, ``controller_silence``, ``new_session``).
        refused: refused measurements, by reason (each counted once per measurement and reason).
        dropped: dropped datagrams, by reason.
        late_replies: replies that left more than ``link.late_reply_ms`` after their
            ``EgmRobot`` arrived.
        superseded: valid ``EgmRobot`` left unanswered because a newer one was already queued.
        robot_missing: ``EgmRobot`` sequence numbers never seen (gaps in ``header.seqno``
            that the session accepted at once; a confirmed far jump is not counted).
        sessions: controller sessions started (the first datagram, then confirmed restarts).
        jumps: far jumps ahead in ``header.seqno`` believed after confirmation.
        kernel_dropped: datagrams the kernel dropped on the link's socket because its receive
            buffer was full (Linux ``SO_RXQ_OVFL``; cumulative, as the last datagram read
            reported it; 0 where the kernel does not report it).
        watchdog_trips: times the watchdog started holding (measurements stopped).
        controller_silences: times the controller stopped sending for longer than
            ``safety.watchdog_ms``; the first reply after one is a hold.
        send_errors: replies the socket refused.
        latency_ms: reply latency samples, ms (kernel receive time to after ``sendto``).
        late_log: the most recent late replies (superseded ``EgmRobot`` included), each split
            into where its time went (:class:`LateReply`): tells a machine that took the CPU
            away from the link from a link that was too slow.
    """

    received: int = 0
    sent: int = 0
    commands: int = 0
    holds: collections.Counter[str] = field(default_factory=collections.Counter)
    refused: collections.Counter[str] = field(default_factory=collections.Counter)
    dropped: collections.Counter[str] = field(default_factory=collections.Counter)
    late_replies: int = 0
    superseded: int = 0
    robot_missing: int = 0
    sessions: int = 0
    jumps: int = 0
    kernel_dropped: int = 0
    watchdog_trips: int = 0
    controller_silences: int = 0
    send_errors: int = 0
    latency_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    late_log: collections.deque[LateReply] = field(
        default_factory=lambda: collections.deque(maxlen=10_000))

    def latency_summary(self) -> dict[str, float]:
        """Reply latency ``p50``, ``p99``, ``max`` and ``mean`` in ms (NaN without samples)."""
        return latency_summary(self.latency_ms)

    def copy(self) -> EgmStats:
        return copy_stats(self)

    def as_dict(self) -> dict[str, Any]:
        """Plain numbers (counters as dicts, latency as its summary) for printing or JSON."""
        return {"received": self.received, "sent": self.sent, "commands": self.commands,
                "holds": dict(self.holds), "refused": dict(self.refused),
                "dropped": dict(self.dropped), "late_replies": self.late_replies,
                "superseded": self.superseded, "robot_missing": self.robot_missing,
                "sessions": self.sessions, "jumps": self.jumps,
                "kernel_dropped": self.kernel_dropped,
                "watchdog_trips": self.watchdog_trips,
                "controller_silences": self.controller_silences, "send_errors": self.send_errors,
                "latency_ms": self.latency_summary()}


def copy_stats(stats: Any) -> Any:
    """A copy of a stats dataclass whose counters and sample deques are independent."""
    out = dataclasses.replace(stats)
    for f in dataclasses.fields(stats):
        v = getattr(stats, f.name)
        if isinstance(v, collections.Counter):
            setattr(out, f.name, collections.Counter(v))
        elif isinstance(v, collections.deque):
            setattr(out, f.name, collections.deque(v, maxlen=v.maxlen))
    return out


def latency_summary(samples: Any) -> dict[str, float]:
    """``p50``, ``p99``, ``max``, ``mean`` of latency samples in ms (NaN when empty)."""
    a = np.fromiter(samples, dtype=float)
    if a.size == 0:
        return {"n": 0, "p50": math.nan, "p99": math.nan, "max": math.nan, "mean": math.nan}
    return {"n": int(a.size), "p50": float(np.percentile(a, 50)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max()), "mean": float(a.mean())}


# --------------------------------------------------------------------------- wire helpers

def _finite(values: Any) -> bool:
    return all(math.isfinite(v) for v in values)


def _pose_values(pose: Any) -> list[float]:
    out: list[float] = []
    if pose.HasField("pos"):
        out += (pose.pos.x, pose.pos.y, pose.pos.z)
    if pose.HasField("orient"):
        o = pose.orient
        out += (o.u0, o.u1, o.u2, o.u3)
    if pose.HasField("euler"):
        out += (pose.euler.x, pose.euler.y, pose.euler.z)
    return out


def _check_size(data: bytes, max_bytes: int) -> str:
    if not data:
        return "empty"
    if len(data) > max_bytes:
        return "oversized"
    return ""


def parse_robot(data: bytes, max_bytes: int = 1024) -> tuple[Any | None, str]:
    """Parse and validate one datagram as ``EgmRobot``.

    Returns:
        ``(message, "")`` or ``(None, reason)`` with reason one of ``empty``, ``oversized``,
        ``unparseable``, ``wrong_type`` (no header or ``mtype`` is not ``MSGTYPE_DATA``; the
        protocol is not self-describing, so an ``EgmSensor`` would otherwise parse as an
        ``EgmRobot``), ``missing_required`` (a required field is absent: the protobuf runtime
        does not check nested ones while parsing), ``non_finite`` (a NaN or inf in a joint or
        pose value). Never raises.
    """
    reason = _check_size(data, max_bytes)
    if reason:
        return None, reason
    msg = EgmRobot()
    try:
        msg.ParseFromString(data)
    except Exception:  # DecodeError, missing required fields, anything the runtime raises
        return None, "unparseable"
    if not msg.HasField("header") or msg.header.mtype != EgmHeader.MSGTYPE_DATA:
        return None, "wrong_type"
    if not msg.IsInitialized():  # the runtime's parser does not check nested required fields
        return None, "missing_required"
    values: list[float] = []
    for part in (msg.feedBack, msg.planned):
        values += part.joints.joints
        values += part.externalJoints.joints
        values += _pose_values(part.cartesian)
    if not _finite(values):
        return None, "non_finite"
    return msg, ""


def parse_sensor(data: bytes, mode: str, max_bytes: int = 1024) -> tuple[Any | None, str]:
    """Parse and validate one sensor reply (``EgmSensor`` for ``pose``, ``EgmSensorPathCorr``
    for ``pathcorr``), as the controller side does.

    Returns ``(message, "")`` or ``(None, reason)``: ``empty``, ``oversized``, ``unparseable``,
    ``wrong_type`` (``mtype`` not ``MSGTYPE_CORRECTION`` / ``MSGTYPE_PATH_CORRECTION``),
    ``missing_required``, ``incomplete`` (no pose / no correction), ``non_finite``. Never raises.
    """
    reason = _check_size(data, max_bytes)
    if reason:
        return None, reason
    pose_mode = mode == "pose"
    msg = EgmSensor() if pose_mode else EgmSensorPathCorr()
    try:
        msg.ParseFromString(data)
    except Exception:
        return None, "unparseable"
    want = EgmHeader.MSGTYPE_CORRECTION if pose_mode else EgmHeader.MSGTYPE_PATH_CORRECTION
    if not msg.HasField("header") or msg.header.mtype != want:
        return None, "wrong_type"
    if not msg.IsInitialized():
        return None, "missing_required"
    if pose_mode:
        c = msg.planned.cartesian
        if not (msg.HasField("planned") and msg.planned.HasField("cartesian")
                and c.HasField("pos") and (c.HasField("orient") or c.HasField("euler"))):
            return None, "incomplete"
        values = _pose_values(c)
    else:
        if not msg.HasField("pathCorr"):
            return None, "incomplete"
        p = msg.pathCorr.pos
        values = [p.x, p.y, p.z]
    if not _finite(values):
        return None, "non_finite"
    return msg, ""


# --------------------------------------------------------------------------- the link

@dataclass(frozen=True)
class _Measurement:
    ident: int
    vec: np.ndarray            # pose: position mm; pathcorr: offset mm
    quat: np.ndarray | None    # pose: unit quaternion (w, x, y, z)
    measured_at: float         # clock seconds
    arrived_at: float          # clock seconds


class EgmLink:
    """The sensor end of an EGM session.

    Args:
        config: the EGM configuration (default ``configs/egm.yaml``).
        gate: reachability check for poses, ``gate(position_mm, quaternion) -> (ok, reason)``;
            called from the thread that calls ``set_target`` / ``set_correction``, never from
            the 4 ms reply path. In pathcorr mode it needs the corrected torch pose passed to
            :meth:`set_correction`; without one the correction is refused.
        clock: seconds, monotonic; measurement times are on this clock (tests pass a fake).
        bind: open the UDP socket now (``False``: only :meth:`handle_datagram` is used).

    Use as a context manager or ``start()`` / ``stop()``; :attr:`address` is the bound address
    (port 0 in the config binds an ephemeral port).
    """

    def __init__(self, config: EgmConfig | None = None, *, gate: Gate | None = None,
                 clock: Callable[[], float] = time.monotonic, bind: bool = True) -> None:
        self.config = config or load_egm_config()
        self.mode = self.config.mode
        self.gate = gate
        self._clock = clock
        self._safety = self.config.safety
        self._max_bytes = self.config.link.max_datagram_bytes
        self._lock = threading.Lock()
        self._stats = EgmStats(latency_ms=collections.deque(
            maxlen=self.config.link.latency_samples))
        self._meas: _Measurement | None = None
        self._next_ident = 0
        self._logged: set[tuple[int, str]] = set()
        self._watchdog_holding = False
        self._seqno = 0
        self._t0 = clock()
        lk = self.config.link
        self._tracker = SequenceTracker(
            reorder_window=lk.reorder_window, max_gap=lk.max_gap,
            min_period_s=lk.min_period_ms / 1e3, confirm=lk.session_confirm,
            silence_s=lk.session_silence_ms / 1e3)
        self._last_rx_time: float | None = None   # clock s of the last valid EgmRobot
        self._controller_silent = False
        self._resync = False       # the next reply holds: the controller was silent
        self._new_session = False  # the next reply holds on the new session's start pose
        self._peer_port = self.config.network.controller_port or None
        # last sent command (the reference of the next step and what a hold commands): pose
        # (position, quaternion) or pathcorr offset; None at the start of a session
        self._sent_vec: np.ndarray | None = None
        self._sent_quat: np.ndarray | None = None
        # pose mode: the fed-back pose of the datagram that started the session (its checks
        # passed); the first reply of the session holds there when there is nothing to send
        self._session_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self.realtime = False  # whether the serving thread got its real-time priority
        if bind:
            self._sock = self._open_socket()

    # ------------------------------------------------------------------ lifecycle

    def _open_socket(self) -> socket.socket:
        net = self.config.network
        family = socket.AF_INET6 if ipaddress.ip_address(net.host).version == 6 else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind((net.host, net.port))
        except OSError as e:
            sock.close()
            hint = " (another EGM sensor running?)" if e.errno == errno.EADDRINUSE else ""
            raise EgmError(f"cannot bind the EGM sensor to {net.host}:{net.port}: "
                           f"{e.strerror or e}{hint}") from None
        sock.setblocking(False)
        if SO_TIMESTAMPNS is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            except OSError:
                pass  # fall back to user-space receive times
        if _SO_RXQ_OVFL is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
            except OSError:
                log.info("EGM: this kernel does not report receive-buffer drops (SO_RXQ_OVFL)")
        if not net.is_loopback:
            log.warning("EGM sensor bound to %s:%d, not loopback: reachable from the network",
                        net.host, net.port)
        return sock

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` the sensor listens on."""
        if self._sock is None:
            raise EgmError("the link was made with bind=False and has no socket")
        host, port = self._sock.getsockname()[:2]
        return host, port

    def start(self) -> EgmLink:
        """Serve in a background thread until :meth:`stop`."""
        if self._sock is None:
            raise EgmError("the link was made with bind=False and has no socket")
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self.serve_forever, name="egm-link",
                                            daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the socket (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> EgmLink:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def serve_forever(self, poll_s: float = 0.05) -> None:
        """Answer datagrams until :meth:`stop` (``poll_s``: how often the stop flag is read).

        Asks for ``link.rt_priority`` for the calling thread first."""
        self.realtime = set_realtime_priority(self.config.link.rt_priority, "EGM link")
        while not self._stop.is_set():
            self.serve_once(poll_s)

    def serve_once(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for datagrams, handle all queued ones, answer the newest
        valid ``EgmRobot``. Returns the number of replies sent (0 or 1)."""
        sock = self._sock
        if sock is None:
            return 0
        try:
            ready, _, _ = select.select([sock], [], [], timeout_s)
        except (OSError, ValueError):  # closed under us by stop()
            return 0
        if not ready:
            self._check_silence(self._clock())
            return 0
        woke_ns, cpu0_ns = time.time_ns(), time.thread_time_ns()
        newest: tuple[Any, tuple[Any, ...], int] | None = None
        first_rx_ns = 0
        while True:
            try:
                data, anc, flags, sender = sock.recvmsg(self._max_bytes + 1, _ANC_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as e:  # e.g. ICMP port unreachable surfacing as ECONNREFUSED
                self._drop(f"socket_error_{e.errno}", sender=None)
                break
            rx_ns = rx_time_ns(anc)
            self._kernel_drops(anc)
            if flags & socket.MSG_TRUNC:
                self._drop("oversized", sender)
                continue
            # its arrival on the link's clock: the kernel's receive time, not when it was read
            # (datagrams read in one batch after a stall arrived a period apart)
            at = self._clock() - max(0, time.time_ns() - rx_ns) / 1e9
            robot = self._accept(data, sender, at)
            if robot is not None:
                if newest is not None:
                    with self._lock:
                        self._stats.superseded += 1
                else:
                    first_rx_ns = rx_ns
                newest = (robot, sender, rx_ns)
        if newest is None:
            return 0
        robot, sender, rx_ns = newest
        reply = self._answer(robot)
        try:
            sock.sendto(reply, sender)
        except OSError as e:
            with self._lock:
                self._stats.send_errors += 1
            log.warning("EGM reply to %s failed: %s", sender, e)
            return 0
        tx_ns, cpu_ns = time.time_ns(), time.thread_time_ns() - cpu0_ns
        self._count_sent((tx_ns - rx_ns) / 1e6)
        if (tx_ns - first_rx_ns) / 1e6 > self.config.link.late_reply_ms:
            entry = LateReply(first_rx_ns, rx_ns, (woke_ns - first_rx_ns) / 1e6,
                              (tx_ns - woke_ns) / 1e6, cpu_ns / 1e6)
            with self._lock:
                self._stats.late_log.append(entry)
        return 1

    # ------------------------------------------------------------------ measurements

    def set_target(self, position_mm: ArrayLike, quaternion: ArrayLike,
                   measured_at: float | None = None) -> Verdict:
        """Pose mode: the TCP target in the base frame (mm; unit quaternion w, x, y, z).

        ``measured_at`` is when the measurement behind it was taken, on the link's clock
        (default: now). A refused target is logged, counted and not stored: the previous one
        stays in force and ages towards the watchdog. Returns the verdict.
        """
        if self.mode != "pose":
            raise EgmError("set_target needs mode: pose (this link runs pathcorr; use "
                           "set_correction)")
        now = self._clock()
        t = now if measured_at is None else float(measured_at)
        p = np.asarray(position_mm, dtype=float).reshape(-1)
        q = np.asarray(quaternion, dtype=float).reshape(-1)
        verdict = self._static_checks(p, q, t, now)
        if verdict.ok:
            assert q is not None
            q = q / np.linalg.norm(q)
            verdict = self._gate(p, q)
        return self._store(verdict, p, q if verdict.ok else None, t, now)

    def prepare(self, position_mm: ArrayLike, quaternion: ArrayLike) -> None:
        """Pose mode: let the gate check a target that :meth:`set_target` will probably get
        soon, now, off the control path (a gate with a ``prepare`` method, such as
        :class:`~torchseam.robot.reach.ReachGate`; others ignore it). Nothing is sent or
        stored: :meth:`set_target` still runs every check, the gate's answer for that very
        pose just comes ready."""
        ready = getattr(self.gate, "prepare", None)
        if self.mode != "pose" or ready is None:
            return
        p = np.asarray(position_mm, dtype=float).reshape(-1)
        q = np.asarray(quaternion, dtype=float).reshape(-1)
        if not (p.shape == (3,) and q.shape == (4,) and np.isfinite(q).all()
                and abs(float(np.linalg.norm(q)) - 1.0) <= _QUAT_TOL):
            return  # set_target refuses it before the gate
        try:
            ready(p.copy(), q / np.linalg.norm(q))  # what set_target hands the gate
        except Exception as e:  # noqa: BLE001 - advisory: set_target runs (and refuses) it
            log.debug("gate prepare raised %r; set_target will check the pose", e)

    def set_correction(self, offset_mm: ArrayLike, measured_at: float | None = None,
                       pose: tuple[ArrayLike, ArrayLike] | None = None) -> Verdict:
        """Pathcorr mode: the seam's offset from the programmed path in the path frame, mm.

        ``measured_at``: when the measurement was taken, on the link's clock (default: now);
        its age travels in ``EgmPathCorr.age``. ``pose``: the corrected torch pose
        ``(position_mm, quaternion)`` in the base frame, for the ``gate``. Returns the verdict.
        """
        if self.mode != "pathcorr":
            raise EgmError("set_correction needs mode: pathcorr (this link runs pose; use "
                           "set_target)")
        now = self._clock()
        t = now if measured_at is None else float(measured_at)
        c = np.asarray(offset_mm, dtype=float).reshape(-1)
        verdict = self._static_checks(c, None, t, now)
        if verdict.ok and self.gate is not None:
            if pose is None:
                verdict = Verdict(False, "no_gate_pose",
                                  "a reachability gate is set but no corrected pose was given")
            else:
                gp = np.asarray(pose[0], dtype=float).reshape(-1)
                gq = np.asarray(pose[1], dtype=float).reshape(-1)
                verdict = self._static_checks(gp, gq, t, now)
                if verdict.ok:
                    verdict = self._gate(gp, gq / np.linalg.norm(gq))
        return self._store(verdict, c, None, t, now)

    def clear_measurement(self) -> None:
        """Forget the current measurement: the link holds the robot from the next cycle."""
        self._meas = None

    def _static_checks(self, v: np.ndarray, q: np.ndarray | None, t: float,
                       now: float) -> Verdict:
        s = self._safety
        if v.shape != (3,) or (q is not None and q.shape != (4,)):
            return Verdict(False, "bad_shape", f"expected 3 position and 4 quaternion values, "
                           f"got {v.shape} and {None if q is None else q.shape}")
        if not (np.isfinite(v).all() and (q is None or np.isfinite(q).all())
                and math.isfinite(t)):
            return Verdict(False, "non_finite", f"NaN or inf in {v}, {q}, t={t}")
        if q is not None and abs(float(np.linalg.norm(q)) - 1.0) > _QUAT_TOL:
            return Verdict(False, "bad_quaternion",
                           f"quaternion norm {np.linalg.norm(q):.6f} is not 1")
        if self.mode == "pathcorr" and q is None:
            norm = float(np.linalg.norm(v))
            if norm > s.max_correction_mm:
                return Verdict(False, "correction_too_large",
                               f"correction {norm:.3f} mm > max_correction_mm "
                               f"{s.max_correction_mm}")
        return self._age_check(t, now)

    def _age_check(self, t: float, now: float) -> Verdict:
        age_ms = (now - t) * 1e3
        if age_ms > self._safety.max_age_ms:
            return Verdict(False, "stale", f"measurement is {age_ms:.1f} ms old > max_age_ms "
                           f"{self._safety.max_age_ms}")
        if age_ms < -1.0:  # a clock mix-up, not a measurement from the future
            return Verdict(False, "future_timestamp",
                           f"measurement time lies {-age_ms:.1f} ms in the future")
        return ACCEPTED

    def _gate(self, p: np.ndarray, q: np.ndarray) -> Verdict:
        if self.gate is None:
            return ACCEPTED
        try:
            ok, why = self.gate(p.copy(), q.copy())
        except Exception as e:  # a failing gate refuses; it never opens
            return Verdict(False, "gate_error", f"reachability gate raised {e!r}")
        if not ok:
            return Verdict(False, "gate", f"unreachable: {why}")
        return ACCEPTED

    def _store(self, verdict: Verdict, v: np.ndarray, q: np.ndarray | None, t: float,
               now: float) -> Verdict:
        with self._lock:
            ident = self._next_ident
            self._next_ident += 1
        if not verdict.ok:
            self._refuse(ident, verdict)
            return verdict
        self._meas = _Measurement(ident, v.copy(), None if q is None else q.copy(), t, now)
        return verdict

    def _refuse(self, ident: int, verdict: Verdict) -> None:
        key = (ident, verdict.reason)
        with self._lock:
            if key in self._logged:
                return
            if len(self._logged) > 10_000:  # bounded: only recent keys matter
                self._logged.clear()
            self._logged.add(key)
            self._stats.refused[verdict.reason] += 1
        log.warning("EGM refused measurement %d: %s (%s)", ident, verdict.reason,
                    verdict.detail)

    # ------------------------------------------------------------------ datagrams

    def handle_datagram(self, data: bytes, sender: tuple[Any, ...]) -> bytes | None:
        """Validate one datagram and return the reply to send to ``sender`` (``None``: dropped).

        The socket-free core of the link (the thread uses the same steps); counts the reply as
        sent. Never raises on any input.
        """
        t0 = time.perf_counter_ns()
        robot = self._accept(data, sender)
        if robot is None:
            return None
        reply = self._answer(robot)
        self._count_sent((time.perf_counter_ns() - t0) / 1e6)
        return reply

    def _drop(self, reason: str, sender: Any) -> None:
        with self._lock:
            self._stats.dropped[reason] += 1
            first = self._stats.dropped[reason] == 1
        # the first of each kind as a warning, the rest at debug: a flood must not flood the log
        detail = _DROP_DETAIL.get(reason)
        log.log(logging.WARNING if first else logging.DEBUG,
                "EGM dropped a datagram from %s: %s%s", sender, reason,
                f" ({detail})" if detail else "")

    def _kernel_drops(self, ancdata: list[tuple[int, int, bytes]]) -> None:
        """Take the socket's drop counter (SO_RXQ_OVFL) from a datagram's ancillary data."""
        n = _rx_overflow(ancdata)
        if n is None:
            return
        with self._lock:
            before = self._stats.kernel_dropped
            if n <= before:
                return
            self._stats.kernel_dropped = n
        log.warning("EGM: the kernel dropped %d datagram(s) on the link's socket (receive "
                    "buffer full; %d in all): the link did not read fast enough", n - before, n)

    def _accept(self, data: bytes, sender: tuple[Any, ...], at: float | None = None) -> Any | None:
        """Validate one datagram; the ``EgmRobot`` to answer, or None (dropped and counted).
        ``at``: its arrival on the link's clock (default: now)."""
        net = self.config.network
        try:
            host, port = str(sender[0]), int(sender[1])
            foreign = ipaddress.ip_address(host) != ipaddress.ip_address(net.controller_host)
        except (ValueError, TypeError, IndexError):
            foreign = True
            port = -1
        if not foreign and self._peer_port is not None and port != self._peer_port:
            foreign = True
        if foreign:
            self._drop("foreign_sender", sender)
            return None
        robot, reason = parse_robot(data, self._max_bytes)
        if robot is None:
            self._drop(reason, sender)
            return None
        if not robot.header.HasField("seqno"):
            self._drop("no_seqno", sender)
            return None
        clock_us, reason = feedback_clock_us(robot)
        if clock_us is None:
            self._drop(reason, sender)
            return None
        fb_pose = None
        if self.mode == "pose":  # pose mode cannot hold at a session start without it
            fb_pose, reason = feedback_pose(robot)
            if fb_pose is None:
                self._drop(reason, sender)
                return None
        now = self._clock()
        decision = self._tracker.decide(robot.header.seqno, clock_us, now if at is None else at)
        if decision.action == DROP:
            self._drop(decision.reason, sender)
            return None
        if decision.action == NEW_SESSION:
            self._start_session(decision.reason, fb_pose, robot.header.seqno)
        elif decision.reason == "jump":
            with self._lock:
                self._stats.jumps += 1
            log.warning("EGM controller seqno jumped ahead to %d: believed after %d consistent "
                        "datagrams and a silent session", robot.header.seqno,
                        self.config.link.session_confirm)
        elif decision.missing:
            with self._lock:
                self._stats.robot_missing += decision.missing
        if self._peer_port is None:
            self._peer_port = port
            log.info("EGM session locked onto controller %s:%d", host, port)
        self._check_silence(now)
        if self._controller_silent:
            log.info("EGM controller is back after %.0f ms: holding for one cycle",
                     (now - (self._last_rx_time or now)) * 1e3)
            self._resync = True
            self._controller_silent = False
        self._last_rx_time = now
        with self._lock:
            self._stats.received += 1
        return robot

    def _start_session(self, why: str, fb_pose: tuple[np.ndarray, np.ndarray] | None,
                       seq: int) -> None:
        """A controller session starts: the last command is no reference any more; the
        fed-back pose of this datagram (which passed every check of a session start) is."""
        with self._lock:
            self._stats.sessions += 1
        self._session_pose = fb_pose
        if why == "first":
            return
        log.warning("EGM controller restarted (seqno and feedBack.time both restarted, "
                    "consistently, after a silence): new session at seqno %d; the first reply "
                    "holds on its start pose", seq)
        self._sent_vec = self._sent_quat = None
        self._new_session = True

    def _check_silence(self, now: float) -> None:
        """Flag (once) a controller that stopped sending for longer than the watchdog."""
        last = self._last_rx_time
        if last is None or self._controller_silent:
            return
        gap_ms = (now - last) * 1e3
        if gap_ms > self._safety.watchdog_ms:
            self._controller_silent = True
            with self._lock:
                self._stats.controller_silences += 1
            log.warning("EGM controller silent for %.0f ms (> watchdog_ms %.0f)", gap_ms,
                        self._safety.watchdog_ms)

    # ------------------------------------------------------------------ replies

    def _answer(self, robot: Any) -> bytes:
        now = self._clock()
        meas = self._meas
        s = self._safety
        if self._new_session:  # a restarted controller: hold on the session's start pose
            self._new_session = self._resync = False
            hold, verdict = "new_session", ACCEPTED
        elif self._resync:  # after a controller silence: hold the last accepted command once
            self._resync = False
            hold, verdict = "controller_silence", ACCEPTED
        elif meas is None:
            hold, verdict = "no_measurement", ACCEPTED
        elif (now - meas.arrived_at) * 1e3 > s.watchdog_ms:
            hold, verdict = "watchdog", ACCEPTED
        else:
            hold = ""
            verdict = self._age_check(meas.measured_at, now)
            if verdict.ok:
                verdict = self._step_check(meas, robot)
            if not verdict.ok:
                self._refuse(meas.ident, verdict)
                hold = "refused"
        self._watchdog_state(hold == "watchdog", now, meas)
        if self.mode == "pose":
            msg = self._pose_reply(meas, hold)
        else:
            msg = self._pathcorr_reply(meas, hold, now)
        with self._lock:
            if hold:
                self._stats.holds[hold] += 1
            else:
                self._stats.commands += 1
        return msg.SerializeToString()

    def _watchdog_state(self, holding: bool, now: float, meas: _Measurement | None) -> None:
        if holding and not self._watchdog_holding:
            assert meas is not None
            with self._lock:
                self._stats.watchdog_trips += 1
            log.warning("EGM watchdog: no measurement for %.0f ms (> %.0f ms): holding the robot",
                        (now - meas.arrived_at) * 1e3, self._safety.watchdog_ms)
        elif not holding and self._watchdog_holding:
            log.info("EGM watchdog: measurements are back, guiding again")
        self._watchdog_holding = holding

    def _reference_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Pose mode: what the next step is measured from and what a hold commands."""
        ref = None if self._sent_vec is None else (self._sent_vec, self._sent_quat)
        return hold_pose(ref, self._session_pose)  # type: ignore[arg-type]

    def _step_check(self, meas: _Measurement, robot: Any) -> Verdict:
        s = self._safety
        if self.mode == "pose":
            ref_p, ref_q = self._reference_pose()
            step = float(np.linalg.norm(meas.vec - ref_p))
            if step > s.max_step_mm:
                return Verdict(False, "step_too_large",
                               f"target moves {step:.3f} mm > max_step_mm {s.max_step_mm}")
            assert meas.quat is not None
            turn = quat_angle_deg(meas.quat, ref_q)
            if turn > s.max_step_deg:
                return Verdict(False, "rotation_step_too_large",
                               f"target turns {turn:.3f} deg > max_step_deg {s.max_step_deg}")
            fb = robot.feedBack.cartesian  # may only refuse: it comes from the wire
            lead = float(np.linalg.norm(meas.vec - np.array([fb.pos.x, fb.pos.y, fb.pos.z])))
            if lead > s.max_lead_mm:
                return Verdict(False, "too_far_from_robot",
                               f"target is {lead:.3f} mm from the robot > max_lead_mm "
                               f"{s.max_lead_mm}")
            return ACCEPTED
        ref = self._sent_vec if self._sent_vec is not None else np.zeros(3)
        step = float(np.linalg.norm(meas.vec - ref))
        if step > s.max_step_mm:
            return Verdict(False, "step_too_large",
                           f"correction changes by {step:.3f} mm > max_step_mm {s.max_step_mm}")
        return ACCEPTED

    def _within_step(self, vec: np.ndarray, quat: np.ndarray | None) -> bool:
        """Is a reply within max_step_mm / max_step_deg of the previous one (the last check
        before the wire; a command passed the same check against the same reference)?"""
        if self._sent_vec is None:
            return True
        mm, deg = reply_step(self._sent_vec, vec, self._sent_quat, quat)
        s = self._safety
        return mm <= s.max_step_mm * (1 + 1e-9) and deg <= s.max_step_deg * (1 + 1e-9)

    def _header(self, msg: Any, mtype: int) -> None:
        self._seqno = (self._seqno + 1) & _U32
        msg.header.seqno = self._seqno
        msg.header.tm = int((self._clock() - self._t0) * 1e3) & _U32
        msg.header.mtype = mtype

    def _pose_reply(self, meas: _Measurement | None, hold: str) -> Any:
        if not hold:
            assert meas is not None and meas.quat is not None
            p, q = meas.vec, meas.quat
            if not self._within_step(p, q):  # unreachable: _step_check used this reference
                p, q = self._reference_pose()
        else:  # the last accepted pose; at a session start, its start pose
            p, q = self._reference_pose()
        msg = EgmSensor()
        self._header(msg, EgmHeader.MSGTYPE_CORRECTION)
        c = msg.planned.cartesian
        c.pos.x, c.pos.y, c.pos.z = (float(x) for x in p)
        c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = (float(x) for x in q)
        self._sent_vec, self._sent_quat = p.copy(), q.copy()
        self._session_pose = None  # the reference from now on is the last reply
        return msg

    def _pathcorr_reply(self, meas: _Measurement | None, hold: str, now: float) -> Any:
        held = self._sent_vec if self._sent_vec is not None else np.zeros(3)
        if hold:
            offset, age = held, 0
        else:
            assert meas is not None
            offset = meas.vec
            age = max(0, int(round((now - meas.measured_at) * 1e3)))
            if not self._within_step(offset, None):  # unreachable: _step_check did it
                offset, age = held, 0
        msg = EgmSensorPathCorr()
        self._header(msg, EgmHeader.MSGTYPE_PATH_CORRECTION)
        pc = msg.pathCorr
        pc.pos.x, pc.pos.y, pc.pos.z = (float(x) for x in offset)
        pc.age = min(age, _U32)
        self._sent_vec = offset.copy()
        return msg

    def _count_sent(self, latency_ms: float) -> None:
        with self._lock:
            self._stats.sent += 1
            self._stats.latency_ms.append(latency_ms)
            if latency_ms > self.config.link.late_reply_ms:
                self._stats.late_replies += 1

    # ------------------------------------------------------------------ inspection

    @property
    def stats(self) -> EgmStats:
        """A consistent copy of the counters."""
        with self._lock:
            return self._stats.copy()

    @property
    def holding(self) -> bool:
        """True while the watchdog holds the robot."""
        return self._watchdog_holding


def set_realtime_priority(priority: int, what: str) -> bool:
    """Give the calling thread SCHED_FIFO ``priority`` (Linux; 0 does nothing).

    Returns whether it was granted; a refusal (no CAP_SYS_NICE, no RT budget in the cgroup,
    another OS) is logged as a warning and the thread goes on at normal priority.
    """
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # 0: this thread
    except (AttributeError, OSError) as e:
        log.warning("%s: real-time priority %d refused (%s): running at normal priority", what,
                    priority, e)
        return False
    log.info("%s: running at SCHED_FIFO priority %d", what, priority)
    return True


def _rx_overflow(ancdata: list[tuple[int, int, bytes]]) -> int | None:
    """The socket's drop counter (SO_RXQ_OVFL) from ancillary data, or None (not reported)."""
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == _SO_RXQ_OVFL and len(data) >= 4:
            return int(_U32_STRUCT.unpack_from(data)[0])
    return None


def rx_time_ns(ancdata: list[tuple[int, int, bytes]]) -> int:
    """Kernel receive time (CLOCK_REALTIME ns) from SO_TIMESTAMPNS, else now."""
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= 16:
            sec, nsec = TIMESPEC.unpack_from(data)
            return sec * 1_000_000_000 + nsec
    return time.time_ns()
