"""Sensor side of ABB Externally Guided Motion (EGM) over UDP, with the safety of issue 6.

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
- a step larger than ``safety.max_step_mm`` (``max_step_deg`` for orientation) from the last
  sent command, or, before anything was sent, from the robot's fed-back pose (pathcorr: from
  a zero offset); in pose mode a target further than ``safety.max_lead_mm`` from the fed-back
  TCP;
- a measurement older than ``safety.max_age_ms`` when the reply leaves.

A refused measurement is logged and counted once (not once per 4 ms cycle it stays refused).

Instead of a refused command the link sends a *hold*; the watchdog sends holds as well when no
new measurement arrived for ``safety.watchdog_ms`` (and before the first one):

- pose mode: after a refusal, the last sent target again (the robot finishes the last vetted
  move, and one bad measurement does not strand the tracker); on the watchdog or before the
  first measurement, the robot's own fed-back TCP pose (the robot stops where it is);
- pathcorr mode: the last sent offset again (zero before the first), with age 0: a hold is a
  command, not a measurement. A zero offset is *not* a hold under EGM's absolute semantics:
  it would pull the torch back onto the programmed path by up to ``max_correction_mm``. The
  programmed path itself keeps running; stopping it is RAPID's job.

When the controller falls silent for longer than ``safety.watchdog_ms`` the link logs it, and
answers its first ``EgmRobot`` afterwards with a hold (pose mode: the fed-back pose, which also
becomes the reference of the next step): the robot may have moved or stopped meanwhile.

Datagrams that are oversized, empty, unparseable, of the wrong type (``header.mtype`` not
``DATA``), missing a required field, non-finite, from a foreign sender, duplicated or older
than the newest seen (reordered) are counted by reason and dropped; they never raise out of
the loop. The first of each reason is logged as a warning, the rest at debug level.

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

log = logging.getLogger("torchseam.robot.egm")

#: ``gate(position_mm (3,), quaternion_wxyz (4,)) -> (ok, reason)``: may the TCP go there?
Gate = Callable[[np.ndarray, np.ndarray], "tuple[bool, str]"]

_U32 = 0xFFFFFFFF
# Linux: kernel receive time stamps on a datagram socket (SO_TIMESTAMPNS, CLOCK_REALTIME).
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35) if sys.platform == "linux" else None
_TIMESPEC = struct.Struct("@qq")
_QUAT_TOL = 1e-3  # |q| may differ from 1 by this much (float32 sources, rounding)


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
        received: valid ``EgmRobot`` datagrams.
        sent: replies sent.
        commands: replies that carried an accepted measurement (the rest are holds).
        holds: reply cycles answered with a hold, by cause (``no_measurement``, ``watchdog``,
            ``refused``, ``controller_silence``).
        refused: refused measurements, by reason (each counted once per measurement and reason).
        dropped: dropped datagrams, by reason.
        late_replies: replies that left more than ``link.late_reply_ms`` after their
            ``EgmRobot`` arrived.
        superseded: valid ``EgmRobot`` left unanswered because a newer one was already queued.
        robot_missing: ``EgmRobot`` sequence numbers never seen (gaps in ``header.seqno``).
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
        return _copy_stats(self)

    def as_dict(self) -> dict[str, Any]:
        """Plain numbers (counters as dicts, latency as its summary) for printing or JSON."""
        return {"received": self.received, "sent": self.sent, "commands": self.commands,
                "holds": dict(self.holds), "refused": dict(self.refused),
                "dropped": dict(self.dropped), "late_replies": self.late_replies,
                "superseded": self.superseded, "robot_missing": self.robot_missing,
                "watchdog_trips": self.watchdog_trips,
                "controller_silences": self.controller_silences, "send_errors": self.send_errors,
                "latency_ms": self.latency_summary()}


def _copy_stats(stats: Any) -> Any:
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


def quat_angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    """Rotation angle between two unit quaternions (w, x, y, z), degrees."""
    d = min(1.0, abs(float(np.dot(q1, q2))))
    return math.degrees(2.0 * math.acos(d))


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
        self._last_rx_seq: int | None = None
        self._last_rx_time: float | None = None   # clock s of the last valid EgmRobot
        self._controller_silent = False
        self._resync = False  # the next reply holds: the robot may have moved meanwhile
        self._peer_port = self.config.network.controller_port or None
        # last sent command: pose (position, quaternion) or pathcorr offset
        self._sent_vec: np.ndarray | None = None
        self._sent_quat: np.ndarray | None = None
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
        if _SO_TIMESTAMPNS is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            except OSError:
                pass  # fall back to user-space receive times
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
                data, anc, flags, sender = sock.recvmsg(self._max_bytes + 1, 64)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as e:  # e.g. ICMP port unreachable surfacing as ECONNREFUSED
                self._drop(f"socket_error_{e.errno}", sender=None)
                break
            rx_ns = _rx_time_ns(anc)
            if flags & socket.MSG_TRUNC:
                self._drop("oversized", sender)
                continue
            robot = self._accept(data, sender)
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
        log.log(logging.WARNING if first else logging.DEBUG,
                "EGM dropped a datagram from %s: %s", sender, reason)

    def _accept(self, data: bytes, sender: tuple[Any, ...]) -> Any | None:
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
        if self.mode == "pose" and not (robot.feedBack.HasField("cartesian")
                                        and robot.feedBack.cartesian.HasField("pos")
                                        and robot.feedBack.cartesian.HasField("orient")):
            self._drop("no_feedback_pose", sender)  # pose mode cannot hold without it
            return None
        if robot.header.HasField("seqno"):
            seq = robot.header.seqno
            if self._last_rx_seq is not None:
                diff = (seq - self._last_rx_seq) & _U32
                if diff == 0:
                    self._drop("duplicate", sender)
                    return None
                if diff > _U32 // 2:  # behind the newest
                    if (-diff) & _U32 <= self.config.link.reorder_window:
                        self._drop("out_of_order", sender)
                        return None
                    log.info("EGM controller seqno jumped back %d -> %d: new session",
                             self._last_rx_seq, seq)
                else:
                    with self._lock:
                        self._stats.robot_missing += diff - 1
            self._last_rx_seq = seq
        if self._peer_port is None:
            self._peer_port = port
            log.info("EGM session locked onto controller %s:%d", host, port)
        now = self._clock()
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
        if self._resync:
            # after a controller silence the last sent command is no reference any more:
            # answer with a hold on the robot's own pose and measure the next step from it
            self._resync = False
            self._sent_vec = self._sent_vec if self.mode == "pathcorr" else None
            self._sent_quat = None
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
            msg = self._pose_reply(robot, meas, hold)
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

    def _step_check(self, meas: _Measurement, robot: Any) -> Verdict:
        s = self._safety
        if self.mode == "pose":
            fb = robot.feedBack.cartesian
            fb_p = np.array([fb.pos.x, fb.pos.y, fb.pos.z])
            ref_p = self._sent_vec if self._sent_vec is not None else fb_p
            step = float(np.linalg.norm(meas.vec - ref_p))
            if step > s.max_step_mm:
                return Verdict(False, "step_too_large",
                               f"target moves {step:.3f} mm > max_step_mm {s.max_step_mm}")
            assert meas.quat is not None
            if self._sent_quat is not None:
                ref_q = self._sent_quat
            else:
                o = fb.orient
                ref_q = np.array([o.u0, o.u1, o.u2, o.u3])
                ref_q = ref_q / (np.linalg.norm(ref_q) or 1.0)
            turn = quat_angle_deg(meas.quat, ref_q)
            if turn > s.max_step_deg:
                return Verdict(False, "rotation_step_too_large",
                               f"target turns {turn:.3f} deg > max_step_deg {s.max_step_deg}")
            lead = float(np.linalg.norm(meas.vec - fb_p))
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

    def _header(self, msg: Any, mtype: int) -> None:
        self._seqno = (self._seqno + 1) & _U32
        msg.header.seqno = self._seqno
        msg.header.tm = int((self._clock() - self._t0) * 1e3) & _U32
        msg.header.mtype = mtype

    def _pose_reply(self, robot: Any, meas: _Measurement | None, hold: str) -> Any:
        if not hold:
            assert meas is not None and meas.quat is not None
            p, q = meas.vec, meas.quat
        elif hold == "refused" and self._sent_vec is not None:
            assert self._sent_quat is not None
            p, q = self._sent_vec, self._sent_quat
        else:  # stop where the robot is
            fb = robot.feedBack.cartesian
            p = np.array([fb.pos.x, fb.pos.y, fb.pos.z])
            q = np.array([fb.orient.u0, fb.orient.u1, fb.orient.u2, fb.orient.u3])
        msg = EgmSensor()
        self._header(msg, EgmHeader.MSGTYPE_CORRECTION)
        c = msg.planned.cartesian
        c.pos.x, c.pos.y, c.pos.z = (float(x) for x in p)
        c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = (float(x) for x in q)
        self._sent_vec, self._sent_quat = p.copy(), q.copy()
        return msg

    def _pathcorr_reply(self, meas: _Measurement | None, hold: str, now: float) -> Any:
        if hold:
            offset = self._sent_vec if self._sent_vec is not None else np.zeros(3)
            age = 0
        else:
            assert meas is not None
            offset = meas.vec
            age = max(0, int(round((now - meas.measured_at) * 1e3)))
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


def _rx_time_ns(ancdata: list[tuple[int, int, bytes]]) -> int:
    """Kernel receive time (CLOCK_REALTIME ns) from SO_TIMESTAMPNS, else now."""
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= 16:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return sec * 1_000_000_000 + nsec
    return time.time_ns()
