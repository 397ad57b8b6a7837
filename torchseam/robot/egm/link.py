"""Sensor side of ABB Externally Guided Motion (EGM) over UDP, with the safety of issues 6, 25
and 36.

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
:class:`~torchseam.robot.egm.stats.EgmStats`):

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
(:func:`~torchseam.robot.egm.policy.hold_pose`):

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
:class:`~torchseam.robot.egm.policy.SequenceTracker` from ``header.seqno``, the controller's
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

Whose datagrams: the controller's address is ``network.controller_host`` and
``network.controller_port`` (0: the port of the first valid sender from that host, locked
onto). Anything else is a foreign sender, dropped by its address before it is parsed. A
controller that restarted on a new source port of its host (RobotWare opened its socket again)
is taken back as a new session, never from one datagram
(:class:`~torchseam.robot.egm.policy.PortTracker`): datagrams from another port of the
controller's host are looked at (parsed) only once the session has been silent for
``link.session_silence_ms``; the new port is believed after ``link.session_confirm``
consistent datagrams (sequence numbers and clocks advancing, no clock the old session showed);
the first ``session_confirm - 1`` are dropped as ``unconfirmed_port``, the confirming one is
answered with a hold (``new_session``) on its start pose and the move is logged once
(``EgmStats.controller_moves``). Another host is never taken; nor another port while the
controller talks on its own.

The controller first, whatever else arrives (issue 36: 50 000 datagrams from another local
port in a second, read one by one before each answer, cost the controller 6-8 % of its replies
and 78-96 of its datagrams, dropped by the kernel from the full shared queue). On Linux the
controller gets a socket of its own as soon as its port is known: bound to the link's address
beside the shared, unconnected socket (SO_REUSEADDR on both for that moment, cleared again so
that no other socket can bind the address) and ``connect()``ed to the controller's host and
port, which makes the kernel queue the controller's datagrams there and everything else on the
shared socket. :meth:`EgmLink.serve_once` reads the controller's socket first and answers its
newest valid ``EgmRobot`` at once; only a call with nothing of the controller's to answer reads
the shared socket, at most ``EgmLink.OTHER_BUDGET`` datagrams, and after a call that used the
whole budget it leaves the shared socket alone for ``EgmLink.OTHER_PAUSE_S``: a flood costs
the link a bounded share of its time, delays a controller datagram by one bounded read at
most, and cannot fill the controller's queue (the kernel drops the rest of the flood from the
shared one). A restarted controller's datagrams arrive on the shared socket until its new port
is believed; the controller's socket is then re-connected there. Where the platform does not
give the controller a socket of its own, it shares the one socket with every other sender (read
``EgmLink.CONTROLLER_BUDGET`` datagrams at a time, no pause).

Datagrams that are oversized, empty, unparseable, of the wrong type (``header.mtype`` not
``DATA``), missing a required field, non-finite, without ``header.seqno``, without
``feedBack.time`` (RobotWare before 6.07, which mixes radians and degrees: refused), from a
foreign sender, or refused by the sequence or port policy are counted by reason and dropped;
they never raise out of the loop. The first of each reason is logged as a warning, the rest at
debug level. Every datagram the link reads lands in exactly one counter: ``received`` or one
``dropped`` reason. Datagrams the kernel dropped because a socket's receive buffer was full
(Linux ``SO_RXQ_OVFL``) are counted per socket: ``EgmStats.kernel_dropped_controller`` (the
controller's own; each drop logged as a warning) and ``kernel_dropped_other`` (the shared one;
the first logged), their sum in ``kernel_dropped``. An ICMP port unreachable reported on the
controller's socket (a reply reached a port the controller left) is counted in
``controller_unreachable``, not as a datagram.

The link holds the state (the stored measurement, the last reply, the session's flags) and the
transport (the sockets, the serving thread, the counters); each decision above is a function
or tracker of :mod:`torchseam.robot.egm.policy` that it calls with plain values.

Binding: ``network.host`` (loopback by default); a non-loopback address is logged as a warning.
``link.rt_priority`` asks for SCHED_FIFO for the serving thread. Keep the link out of a process
whose other threads hold the GIL for milliseconds (torch inference): a reply waits for it. While
the link serves, the process's GIL switch interval is ``link.switch_interval_ms`` (Python's
default 5 ms is longer than an EGM cycle), put back when it stops.
"""

from __future__ import annotations

import collections
import errno
import ipaddress
import logging
import os
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from torchseam.core.errors import TorchseamError
from torchseam.robot.egm.config import EgmConfig
from torchseam.robot.egm.messages import EgmHeader, EgmSensor, EgmSensorPathCorr, parse_robot
from torchseam.robot.egm.policy import (
    DROP,
    HOLD_NEW_SESSION,
    HOLD_REFUSED,
    HOLD_SILENCE,
    HOLD_WATCHDOG,
    NEW_SESSION,
    U32,
    Gate,
    PortTracker,
    Pose,
    SeqDecision,
    SequenceTracker,
    Verdict,
    check_age,
    check_correction_step,
    check_gate,
    check_measurement,
    check_pose_step,
    controller_port,
    controller_silent,
    correction_command,
    feedback_clock_us,
    feedback_pose,
    hold_cause,
    hold_pose,
    pose_command,
)
from torchseam.robot.egm.stats import EgmStats, LateReply

log = logging.getLogger("torchseam.robot.egm")  # the package's name: one logger for the link

# Linux: kernel receive time stamps on a datagram socket (SO_TIMESTAMPNS, CLOCK_REALTIME).
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35) if sys.platform == "linux" else None
TIMESPEC = struct.Struct("@qq")
# Linux: the socket's drop counter (receive buffer full) in each datagram's ancillary data
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40) if sys.platform == "linux" else None
_U32_STRUCT = struct.Struct("@I")
_ANC_BYTES = socket.CMSG_SPACE(TIMESPEC.size) + socket.CMSG_SPACE(_U32_STRUCT.size) + 64
# Linux hands a datagram to the socket bound to its address that matches it best: one
# connect()ed to its sender's address and port beats an unconnected one. The controller gets
# such a socket of its own (two sockets bound to one address need SO_REUSEADDR on both)
_OWN_CONTROLLER_SOCKET = sys.platform == "linux"
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
    "foreign_sender": "not the controller's address and port (dropped unread); another port "
                      "of the controller's host is looked at only once the session is silent",
    "unconfirmed_port": "from another port of the controller's host while the session is "
                        "silent: a controller that restarted there is believed after "
                        "link.session_confirm consistent datagrams",
}


class EgmError(TorchseamError):
    """The EGM link cannot run: e.g. its UDP port is taken."""


# --------------------------------------------------------------------------- the link

@dataclass(frozen=True)
class _Measurement:
    ident: int
    vec: np.ndarray            # pose: position mm; pathcorr: offset mm
    quat: np.ndarray | None    # pose: unit quaternion (w, x, y, z)
    measured_at: float         # clock seconds
    arrived_at: float          # clock seconds


@dataclass
class _Batch:
    """What one read of a socket found: the newest accepted ``EgmRobot`` (with its sender and
    kernel receive time, ns), the receive time of the first accepted one, and whether the read
    stopped at its budget (more may be queued)."""

    sock: socket.socket
    newest: tuple[Any, tuple[Any, ...], int] | None = None
    first_rx_ns: int = 0
    full: bool = False


class EgmLink:
    """The sensor end of an EGM session.

    Args:
        config: the EGM configuration; the caller reads it (e.g.
            :func:`~torchseam.robot.egm.config.load_egm_config`), the link reads no file.
        gate: reachability check for poses, ``gate(position_mm, quaternion) -> (ok, reason)``;
            called from the thread that calls ``set_target`` / ``set_correction``, never from
            the 4 ms reply path. In pathcorr mode it needs the corrected torch pose passed to
            :meth:`set_correction`; without one the correction is refused.
        clock: seconds, monotonic; measurement times are on this clock (tests pass a fake).
        bind: open the UDP socket now (``False``: only :meth:`handle_datagram` is used).
        on_robot: called (on the link's thread) with every ``EgmRobot`` the link accepted and
            its arrival on ``clock``, before it is answered: a weld reads the fed-back pose,
            the controller's time and the RAPID data from it. Returns True when this datagram
            starts a new guided motion (RAPID ran ``EGMActPose`` / ``EGMRunPose`` again from
            wherever it moved the robot): the link then starts a new session on it, its first
            reply holding on this datagram's fed-back pose, so nothing from the previous
            motion is commanded. Keep it short: the reply waits for it.
        on_reply: called (on the link's thread) with every outgoing ``EgmSensor`` before it is
            serialised: a weld writes ``RAPIDtoRobot`` (arc request, segment state) into it.

    Use as a context manager or ``start()`` / ``stop()``; :attr:`address` is the bound address
    (port 0 in the config binds an ephemeral port).
    """

    #: datagrams read from the controller's own socket per :meth:`serve_once`
    CONTROLLER_BUDGET = 64
    #: datagrams read from the shared socket (every other sender) per :meth:`serve_once` ...
    OTHER_BUDGET = 32
    #: ... and after a call that used all of it (more were queued), the shared socket is left
    #: alone this long (s): a flood costs the link at most OTHER_BUDGET datagrams per pause
    #: (each dropped by its address, unparsed); the kernel drops the rest
    OTHER_PAUSE_S = 0.001
    #: other ports of the controller's host followed at once as a possible restart
    MAX_PORT_CANDIDATES = 4

    def __init__(self, config: EgmConfig, *, gate: Gate | None = None,
                 clock: Callable[[], float] = time.monotonic, bind: bool = True,
                 on_robot: Callable[[Any, float], bool] | None = None,
                 on_reply: Callable[[Any], None] | None = None) -> None:
        self.config = config
        self._on_robot = on_robot
        self._on_reply = on_reply
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
        # a controller back on another port of its host (issue 36)
        self._ports = PortTracker(
            reorder_window=lk.reorder_window, max_gap=lk.max_gap,
            min_period_s=lk.min_period_ms / 1e3, confirm=lk.session_confirm,
            silence_s=lk.session_silence_ms / 1e3, max_candidates=self.MAX_PORT_CANDIDATES)
        self._host_memo: dict[str, bool] = {}  # sender host -> is the controller's host
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
        self._session_pose: Pose | None = None
        self._thread: threading.Thread | None = None
        self._switch_interval: float | None = None   # the interpreter's own, while serving
        self._stop = threading.Event()
        # the shared socket: bound, unconnected; every sender but the controller (and the
        # controller too until it has a socket of its own)
        self._shared: socket.socket | None = None
        # the controller's own socket: bound to the same address, connect()ed to the
        # controller's host and port, so the kernel queues only its datagrams there
        self._ctrl: socket.socket | None = None
        self._other_paused_until = 0.0  # time.monotonic(): the shared socket rests until then
        self._kernel_seen = {"controller": 0, "other": 0}  # SO_RXQ_OVFL per socket
        self.realtime = False  # whether the serving thread got its real-time priority
        if bind:
            self._shared = self._open_socket()
            if self._peer_port is not None:
                self._connect_controller(self._peer_port)

    # ------------------------------------------------------------------ lifecycle

    def _open_socket(self) -> socket.socket:
        net = self.config.network
        sock = open_udp((net.host, net.port), "the EGM sensor",
                        " (another EGM sensor running?)")
        _ask_drop_counter(sock)
        if not net.is_loopback:
            log.warning("EGM sensor bound to %s:%d, not loopback: reachable from the network",
                        net.host, net.port)
        return sock

    def _connect_controller(self, port: int) -> None:
        """Give the controller at ``network.controller_host:port`` a socket of its own (or
        point the one it has at its new port): bound to the link's address with SO_REUSEADDR
        and connected to the controller, so the kernel delivers its datagrams there, in a
        receive buffer no other sender can fill. The shared socket allows the second bind for
        this moment only: with SO_REUSEADDR cleared again on both, no other socket can bind
        the link's address. Where it fails (another platform), the controller shares the
        socket with every other sender, as before."""
        shared = self._shared
        if shared is None or not _OWN_CONTROLLER_SOCKET:
            return
        peer = (self.config.network.controller_host, port)
        if self._ctrl is not None:
            try:
                self._ctrl.connect(peer)
                return
            except OSError as e:
                log.warning("EGM: cannot point the controller's socket at %s:%d (%s): it shares "
                            "the link's socket from now on", *peer, e)
                self._ctrl.close()
                self._ctrl = None
                return
        ctrl = None
        try:
            shared.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                host, bound = shared.getsockname()[:2]
                ctrl = open_udp((host, bound), "the EGM controller's socket", reuse=True)
            finally:
                shared.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
            ctrl.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
            _ask_drop_counter(ctrl)
            ctrl.connect(peer)
        except (OSError, EgmError) as e:
            if ctrl is not None:
                ctrl.close()
            log.warning("EGM: no socket of its own for the controller %s:%d (%s): it shares the "
                        "link's socket with every other sender", *peer, e)
            return
        self._ctrl = ctrl

    @property
    def _sock(self) -> socket.socket | None:
        """The socket the controller's datagrams arrive on: its own once it has one, else the
        shared one (None: made with ``bind=False``, or stopped)."""
        return self._ctrl if self._ctrl is not None else self._shared

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` the sensor listens on."""
        if self._shared is None:
            raise EgmError("the link was made with bind=False and has no socket")
        host, port = self._shared.getsockname()[:2]
        return host, port

    def start(self) -> EgmLink:
        """Serve in a background thread until :meth:`stop`."""
        if self._shared is None:
            raise EgmError("the link was made with bind=False and has no socket")
        if self._thread is None:
            self._stop.clear()
            ms = self.config.link.switch_interval_ms
            if ms > 0 and ms / 1e3 < sys.getswitchinterval():
                # the serving thread gets the interpreter within ``ms`` of a datagram even
                # while another thread runs Python (the process-wide setting, put back at stop)
                self._switch_interval = sys.getswitchinterval()
                sys.setswitchinterval(ms / 1e3)
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
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None
        for sock in (self._ctrl, self._shared):
            if sock is not None:
                sock.close()
        self._ctrl = self._shared = None

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
        """Wait up to ``timeout_s`` for datagrams and answer the controller's newest valid
        ``EgmRobot``. Returns the number of replies sent (0 or 1).

        The controller's own socket is read first (up to ``CONTROLLER_BUDGET`` datagrams) and
        its newest valid ``EgmRobot`` answered at once; only a call that has nothing of the
        controller's to answer reads the shared socket, ``OTHER_BUDGET`` datagrams at most
        (dropping every sender but the controller by its address, unparsed); when that budget
        was used up, the shared socket rests for ``OTHER_PAUSE_S``. A flood thus delays a
        controller datagram by one bounded drain at most, and cannot fill its queue."""
        shared, ctrl = self._shared, self._ctrl
        if shared is None:
            return 0
        watch = [ctrl] if ctrl is not None else []
        rest = self._other_paused_until - time.monotonic() if ctrl is not None else 0.0
        if rest > 0.0:
            timeout_s = min(timeout_s, rest)
        else:
            watch.append(shared)
        try:
            ready, _, _ = select.select(watch, [], [], timeout_s)
        except (OSError, ValueError):  # closed under us by stop()
            return 0
        if not ready:
            self._check_silence(self._clock())
            return 0
        woke_ns, cpu0_ns = time.time_ns(), time.thread_time_ns()
        if ctrl is not None and ctrl in ready:
            batch = self._read(ctrl, self.CONTROLLER_BUDGET, "controller")
            if batch.newest is not None:
                return self._reply(batch, woke_ns, cpu0_ns)
        if shared in ready:
            budget = self.OTHER_BUDGET if ctrl is not None else self.CONTROLLER_BUDGET
            batch = self._read(shared, budget, "other")
            if batch.full and self._ctrl is not None:
                self._other_paused_until = time.monotonic() + self.OTHER_PAUSE_S
            if batch.newest is not None:
                return self._reply(batch, woke_ns, cpu0_ns)
        return 0

    def _read(self, sock: socket.socket, budget: int, which: str) -> _Batch:
        """Read up to ``budget`` queued datagrams from ``sock`` (``which``: ``controller`` or
        ``other``, for the kernel's drop counter); every one lands in one counter."""
        batch = _Batch(sock)
        last_anc: list[tuple[int, int, bytes]] | None = None
        now = self._clock()
        n = 0
        while n < budget:
            try:
                data, anc, flags, sender = sock.recvmsg(self._max_bytes + 1, _ANC_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                # a connected socket reports the ICMP port unreachable of an earlier reply: the
                # controller's port is closed (it stopped, or restarted on another port)
                n += 1
                self._unreachable(which)
                continue
            except OSError as e:  # e.g. closed under us by stop()
                self._drop(f"socket_error_{e.errno}", sender=None)
                break
            n += 1
            last_anc = anc
            if flags & socket.MSG_TRUNC:
                self._drop("oversized", sender)
                continue
            if self._admitted_port(sender, now) is None:
                self._drop("foreign_sender", sender)  # by its address, before any parsing
                continue
            rx_ns = rx_time_ns(anc)
            # its arrival on the link's clock: the kernel's receive time, not when it was read
            # (datagrams read in one batch after a stall arrived a period apart)
            at = self._clock() - max(0, time.time_ns() - rx_ns) / 1e9
            robot = self._accept(data, sender, at)
            if robot is not None:
                if batch.newest is not None:
                    with self._lock:
                        self._stats.superseded += 1
                else:
                    batch.first_rx_ns = rx_ns
                batch.newest = (robot, sender, rx_ns)
        batch.full = n >= budget
        if last_anc is not None:  # the counter is cumulative: the newest datagram's is enough
            self._kernel_drops(last_anc, which)
        return batch

    def _reply(self, batch: _Batch, woke_ns: int, cpu0_ns: int) -> int:
        """Answer the newest ``EgmRobot`` of ``batch`` through the socket it came in on."""
        assert batch.newest is not None
        robot, sender, rx_ns = batch.newest
        reply = self._answer(robot)
        sock = batch.sock
        try:
            if sock is self._ctrl:
                try:
                    sock.send(reply)  # connected: to the controller
                except ConnectionRefusedError:  # an earlier ICMP error, reported now: again
                    self._unreachable("controller")
                    sock.send(reply)
            else:
                sock.sendto(reply, sender)
        except OSError as e:
            with self._lock:
                self._stats.send_errors += 1
            log.warning("EGM reply to %s failed: %s", sender, e)
            return 0
        tx_ns, cpu_ns = time.time_ns(), time.thread_time_ns() - cpu0_ns
        self._count_sent((tx_ns - rx_ns) / 1e6)
        if (tx_ns - batch.first_rx_ns) / 1e6 > self.config.link.late_reply_ms:
            entry = LateReply(batch.first_rx_ns, rx_ns, (woke_ns - batch.first_rx_ns) / 1e6,
                              (tx_ns - woke_ns) / 1e6, cpu_ns / 1e6)
            with self._lock:
                self._stats.late_log.append(entry)
        return 1

    def _unreachable(self, which: str) -> None:
        with self._lock:
            self._stats.controller_unreachable += 1
            first = self._stats.controller_unreachable == 1
        log.log(logging.WARNING if first else logging.DEBUG,
                "EGM: the controller's port refused a reply (ICMP port unreachable on the %s "
                "socket): it stopped or moved", which)

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
        verdict = check_measurement(p, q, t, now, self._safety, self.mode)
        if verdict.ok:
            q = q / np.linalg.norm(q)
            verdict = check_gate(self.gate, p, q)
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
        if not check_measurement(p, q, 0.0, 0.0, self._safety, self.mode).ok:
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
        verdict = check_measurement(c, None, t, now, self._safety, self.mode)
        if verdict.ok and self.gate is not None:
            if pose is None:
                verdict = Verdict(False, "no_gate_pose",
                                  "a reachability gate is set but no corrected pose was given")
            else:
                gp = np.asarray(pose[0], dtype=float).reshape(-1)
                gq = np.asarray(pose[1], dtype=float).reshape(-1)
                verdict = check_measurement(gp, gq, t, now, self._safety, self.mode)
                if verdict.ok:
                    verdict = check_gate(self.gate, gp, gq / np.linalg.norm(gq))
        return self._store(verdict, c, None, t, now)

    def clear_measurement(self) -> None:
        """Forget the current measurement: the link holds the robot from the next cycle."""
        self._meas = None

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

    def _kernel_drops(self, ancdata: list[tuple[int, int, bytes]],
                      which: str = "controller") -> None:
        """Take a socket's drop counter (SO_RXQ_OVFL) from a datagram's ancillary data:
        ``which`` socket, ``controller`` (its own) or ``other`` (the shared one)."""
        n = _rx_overflow(ancdata)
        if n is None:
            return
        with self._lock:
            before = self._kernel_seen[which]
            if n <= before:
                return
            self._kernel_seen[which] = n
            self._stats.kernel_dropped += n - before
            if which == "controller":
                self._stats.kernel_dropped_controller += n - before
            else:
                self._stats.kernel_dropped_other += n - before
        if which == "controller" or self._ctrl is None:
            log.warning("EGM: the kernel dropped %d datagram(s) on the link's socket (receive "
                        "buffer full; %d in all): the link did not read fast enough", n - before,
                        n)
        else:  # a flood from other senders: said once, then at debug level
            log.log(logging.WARNING if before == 0 else logging.DEBUG,
                    "EGM: the kernel dropped %d datagram(s) from other senders than the "
                    "controller (%d in all): the link reads them at a bounded rate; the "
                    "controller's own socket is not affected", n - before, n)

    def _sender_port(self, sender: Any) -> int | None:
        """The port of ``sender`` when it sends from ``network.controller_host``, else None. The
        host's verdict is remembered by its text: a flood from one address costs a look-up."""
        try:
            host, port = sender[0], sender[1]
        except (TypeError, IndexError, KeyError):
            return None
        ok = self._host_memo.get(host) if isinstance(host, str) else None
        if ok is None:
            ok = controller_port(sender, self.config.network.controller_host, None) is not None
            if isinstance(host, str):
                if len(self._host_memo) >= 256:  # bounded: many hosts cost a parse each
                    self._host_memo.clear()
                self._host_memo[host] = ok
        if not ok or not isinstance(port, int):
            return None
        return port

    def _admitted_port(self, sender: Any, at: float) -> int | None:
        """The port of ``sender`` when a datagram from it may be parsed at ``at`` (link clock):
        the controller's address and port (any port before the link locked onto one), or
        another port of the controller's host once the session has been silent long enough
        to be looking for a restarted controller (:class:`~.policy.PortTracker`); None: foreign,
        dropped unread."""
        port = self._sender_port(sender)
        if port is None or self._peer_port is None or port == self._peer_port:
            return port
        return port if self._ports.admits(self._tracker, at) else None

    def _accept(self, data: bytes, sender: tuple[Any, ...], at: float | None = None) -> Any | None:
        """Validate one datagram; the ``EgmRobot`` to answer, or None (dropped and counted).
        ``at``: its arrival on the link's clock (default: now)."""
        now = self._clock()
        t = now if at is None else at
        port = self._admitted_port(sender, t)
        if port is None:
            self._drop("foreign_sender", sender)
            return None
        moved = self._peer_port is not None and port != self._peer_port
        parsed = self._parse(data, sender)
        if parsed is None:
            return None
        robot, clock_us, fb_pose = parsed
        seq = robot.header.seqno
        decision: SeqDecision
        if moved:  # another port of the controller's host, the session silent
            decision = self._ports.decide(self._tracker, port, seq, clock_us, t)
        else:
            decision = self._tracker.decide(seq, clock_us, t)
        if decision.action == DROP:
            self._drop(decision.reason, sender)
            return None
        if moved:
            self._move_controller(port, sender, seq, t)
        else:
            self._ports.clear()  # the session speaks: nobody else is the controller
        if self._on_robot is not None and self._on_robot(robot, t):
            # a new guided motion: nothing from the previous one is a reference any more
            with self._lock:
                self._stats.sessions += 1
            self._session_pose = fb_pose
            self._sent_vec = self._sent_quat = None
            self._meas = None
            self._new_session = True
        elif decision.action == NEW_SESSION:
            self._start_session(decision.reason, fb_pose, seq)
        elif decision.reason == "jump":
            with self._lock:
                self._stats.jumps += 1
            log.warning("EGM controller seqno jumped ahead to %d: believed after %d consistent "
                        "datagrams and a silent session", seq,
                        self.config.link.session_confirm)
        elif decision.missing:
            with self._lock:
                self._stats.robot_missing += decision.missing
        if self._peer_port is None:
            self._peer_port = port
            log.info("EGM session locked onto controller %s:%d", sender[0], port)
            self._connect_controller(port)
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

    def _parse(self, data: bytes, sender: Any) -> tuple[Any, int, Pose | None] | None:
        """The ``EgmRobot`` in ``data``, its controller clock (us) and, in pose mode, its
        fed-back pose; None when a check fails (dropped and counted)."""
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
        return robot, clock_us, fb_pose

    def _move_controller(self, port: int, sender: Any, seq: int, at: float) -> None:
        """The controller, silent on its port, came back on ``port`` (confirmed by the port
        tracker): its stream is the session's from now on, its socket points there."""
        old, silent_ms = self._peer_port, (at - self._tracker.last_at) * 1e3
        self._tracker = self._ports.confirmed(port)
        self._peer_port = port
        self._connect_controller(port)
        with self._lock:
            self._stats.controller_moves += 1
        log.warning("EGM controller moved from port %s to %s:%d (silent %.0f ms on its port, "
                    "then %d consistent datagrams from the new one): new session at seqno %d; "
                    "the first reply holds on its start pose", old, sender[0], port, silent_ms,
                    self.config.link.session_confirm, seq)

    def _start_session(self, why: str, fb_pose: Pose | None, seq: int) -> None:
        """A controller session starts: the last command is no reference any more; the
        fed-back pose of this datagram (which passed every check of a session start) is."""
        with self._lock:
            self._stats.sessions += 1
        self._session_pose = fb_pose
        if why == "first":
            return
        self._sent_vec = self._sent_quat = None
        self._new_session = True
        if why == "new_port":  # said by _move_controller
            return
        log.warning("EGM controller restarted (seqno and feedBack.time both restarted, "
                    "consistently, after a silence): new session at seqno %d; the first reply "
                    "holds on its start pose", seq)

    def _check_silence(self, now: float) -> None:
        """Flag (once) a controller that stopped sending for longer than the watchdog."""
        last = self._last_rx_time
        if self._controller_silent or not controller_silent(last, now, self._safety.watchdog_ms):
            return
        self._controller_silent = True
        with self._lock:
            self._stats.controller_silences += 1
        log.warning("EGM controller silent for %.0f ms (> watchdog_ms %.0f)",
                    (now - (last or now)) * 1e3, self._safety.watchdog_ms)

    # ------------------------------------------------------------------ replies

    def _answer(self, robot: Any) -> bytes:
        now = self._clock()
        meas = self._meas
        hold = hold_cause(new_session=self._new_session, resync=self._resync,
                          arrived_at=None if meas is None else meas.arrived_at, now=now,
                          watchdog_ms=self._safety.watchdog_ms)
        if hold in (HOLD_NEW_SESSION, HOLD_SILENCE):  # each holds for one reply
            self._new_session = self._resync = False
        if not hold:
            assert meas is not None
            verdict = self._command_verdict(meas, robot, now)
            if not verdict.ok:
                self._refuse(meas.ident, verdict)
                hold = HOLD_REFUSED
        self._watchdog_state(hold == HOLD_WATCHDOG, now, meas)
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

    def _last_sent_pose(self) -> Pose | None:
        """Pose mode: the last reply of the session (None before the first)."""
        if self._sent_vec is None or self._sent_quat is None:
            return None
        return self._sent_vec, self._sent_quat

    def _command_verdict(self, meas: _Measurement, robot: Any, now: float) -> Verdict:
        """May the stored measurement be commanded in the reply to ``robot`` at ``now``?"""
        s = self._safety
        verdict = check_age(meas.measured_at, now, s.max_age_ms)
        if not verdict.ok:
            return verdict
        if self.mode != "pose":
            return check_correction_step(meas.vec, self._sent_vec, s)
        assert meas.quat is not None
        fb = robot.feedBack.cartesian.pos
        reference = hold_pose(self._last_sent_pose(), self._session_pose)
        return check_pose_step((meas.vec, meas.quat), reference,
                               np.array([fb.x, fb.y, fb.z]), s)

    def _header(self, msg: Any, mtype: int) -> None:
        self._seqno = (self._seqno + 1) & U32
        msg.header.seqno = self._seqno
        msg.header.tm = int((self._clock() - self._t0) * 1e3) & U32
        msg.header.mtype = mtype

    def _pose_reply(self, meas: _Measurement | None, hold: str) -> Any:
        target = None
        if not hold:
            assert meas is not None and meas.quat is not None
            target = (meas.vec, meas.quat)
        # a hold, or a target that fails the last step check (unreachable: the command was
        # checked against this reference), commands the last accepted pose (at a session
        # start its start pose)
        p, q = pose_command(target, self._last_sent_pose(), self._session_pose, self._safety)
        msg = EgmSensor()
        self._header(msg, EgmHeader.MSGTYPE_CORRECTION)
        if self._on_reply is not None:
            self._on_reply(msg)
        c = msg.planned.cartesian
        c.pos.x, c.pos.y, c.pos.z = (float(x) for x in p)
        c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = (float(x) for x in q)
        self._sent_vec, self._sent_quat = p.copy(), q.copy()
        self._session_pose = None  # the reference from now on is the last reply
        return msg

    def _pathcorr_reply(self, meas: _Measurement | None, hold: str, now: float) -> Any:
        if hold:
            offset, age = correction_command(None, now, now, self._sent_vec, self._safety)
        else:
            assert meas is not None
            offset, age = correction_command(meas.vec, meas.measured_at, now, self._sent_vec,
                                             self._safety)
        msg = EgmSensorPathCorr()
        self._header(msg, EgmHeader.MSGTYPE_PATH_CORRECTION)
        pc = msg.pathCorr
        pc.pos.x, pc.pos.y, pc.pos.z = (float(x) for x in offset)
        pc.age = age
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


def open_udp(address: tuple[str, int], what: str, in_use_hint: str = "", *,
             reuse: bool = False) -> socket.socket:
    """A non-blocking UDP socket bound to ``address`` (IPv4 or IPv6 by the host), with kernel
    receive time stamps where the kernel gives them (else user-space receive times are used).
    Both ends of the EGM link open theirs with it, so both time a datagram the same way.
    ``reuse``: set SO_REUSEADDR before binding (a second socket on an address whose socket
    allows it).

    Raises:
        EgmError: the address cannot be bound: ``cannot bind WHAT to HOST:PORT: why`` (with
            ``in_use_hint`` when the port is taken).
    """
    host, port = address
    try:
        v6 = ipaddress.ip_address(host).version == 6
    except ValueError:  # a host name
        v6 = False
    sock = socket.socket(socket.AF_INET6 if v6 else socket.AF_INET, socket.SOCK_DGRAM)
    try:
        if reuse:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
    except OSError as e:
        sock.close()
        hint = in_use_hint if e.errno == errno.EADDRINUSE else ""
        raise EgmError(f"cannot bind {what} to {host}:{port}: {e.strerror or e}{hint}") from None
    sock.setblocking(False)
    if SO_TIMESTAMPNS is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError:
            pass  # fall back to user-space receive times
    return sock


def _ask_drop_counter(sock: socket.socket) -> None:
    """Ask the kernel for the socket's drop counter on each datagram (Linux SO_RXQ_OVFL)."""
    if _SO_RXQ_OVFL is None:
        return
    try:
        sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
    except OSError:
        log.info("EGM: this kernel does not report receive-buffer drops (SO_RXQ_OVFL)")


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
