"""The simulated IRC5 on the wire: its UDP socket, the cycle loop and the lockstep cycle.

:class:`SimController` owns the socket and the thread; the robot it moves is an
:class:`~torchseam.robot.sim_controller.arm.ArmModel`, the faults it puts on the wire a
:class:`~torchseam.robot.sim_controller.faults.FaultPlan`, the datagrams it sends come from
:class:`~torchseam.robot.sim_controller.messages.RobotMessages`.

Each cycle sends, right at its tick, the ``EgmRobot`` prepared during the previous cycle and
then prepares the next one, so the sensor has the whole period to answer; the feedback is thus
one cycle old, as on a real controller. Replies are matched to cycles: the first valid reply
that arrives before the next ``EgmRobot`` leaves gives a latency sample (kernel time stamps on
both ends); a reply more than one period after its ``EgmRobot``, or none before the next one
leaves, is a late reply. Everything is bounded: receive buffers, sample deques, and the wait
per cycle.
"""

from __future__ import annotations

import collections
import logging
import select
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from torchseam.robot.egm import (
    TIMESPEC,
    EgmConfig,
    EgmError,
    open_udp,
    parse_sensor,
    rx_time_ns,
    set_realtime_priority,
)
from torchseam.robot.kinematics import IRB1410
from torchseam.robot.sim_controller.arm import ArmModel
from torchseam.robot.sim_controller.faults import Fault, FaultPlan
from torchseam.robot.sim_controller.messages import RobotMessages, sensor_command
from torchseam.robot.sim_controller.stats import SimStats

log = logging.getLogger(__name__)

# kernel transmit time stamps (Linux, Documentation/networking/timestamping.rst): a software
# stamp as each datagram leaves, reported on the error queue without the payload
_SO_TIMESTAMPING = getattr(socket, "SO_TIMESTAMPING", 37) if sys.platform == "linux" else None
_TX_STAMP_FLAGS = (1 << 1) | (1 << 4) | (1 << 11)  # TX_SOFTWARE | SOFTWARE | OPT_TSONLY


class SimController:
    """Simulated IRC5 EGM endpoint (see the package docstring).

    Args:
        config: EGM configuration (the caller reads ``configs/egm.yaml``, e.g. with
            :func:`~torchseam.robot.egm.load_egm_config`).
        sensor_address: where to send ``EgmRobot`` (default ``network.host:network.port``).
        bind_address: the controller's own address (default ``network.controller_host`` and
            ``network.controller_port``; port 0 binds an ephemeral one, see :attr:`address`).
        mode: ``pose`` or ``pathcorr`` (default the config's).
        robot: the kinematic model, an :class:`~torchseam.robot.kinematics.IRB1410`
            (:func:`~torchseam.robot.kinematics.load_irb1410`: the shipped one).
        tool: TCP pose in the flange frame, 4x4 mm (the cell's torch:
            ``load_cell().tool.matrix()``).
        path: programmed TCP path for pathcorr, (N, 4, 4) mm in the base frame (default a
            straight line from the home pose along ``path_direction``).
        seed: seed of the ``corrupt`` fault's byte flips.
    """

    def __init__(self, config: EgmConfig, *, robot: IRB1410, tool: np.ndarray,
                 sensor_address: tuple[str, int] | None = None,
                 bind_address: tuple[str, int] | None = None,
                 mode: str | None = None, path: np.ndarray | None = None, seed: int = 0
                 ) -> None:
        self.config = config
        net = self.config.network
        self.sim = self.config.sim_controller
        self.mode = mode or self.config.mode
        if self.mode not in ("pose", "pathcorr"):
            raise EgmError(f"mode must be pose or pathcorr, got {self.mode!r}")
        self.sensor_address = sensor_address or (net.host, net.port)
        self.robot = robot
        self.tool = np.asarray(tool, float)
        self.period = self.sim.period_s
        self._max_reply = self.config.link.max_datagram_bytes
        self.arm = ArmModel(self.robot, self.tool, self.sim, self.mode, path)
        self.faults = FaultPlan(2 * self.config.link.max_datagram_bytes, seed)
        self._messages = RobotMessages(self.period, self.arm.quats)

        self._lock = threading.Lock()
        self._stats = SimStats()
        # recent valid replies as (monotonic s, message), for tests and demos
        self.received: collections.deque[tuple[float, Any]] = collections.deque(maxlen=1024)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.realtime = False  # whether the cycle thread got its real-time priority
        self._pending_ns: int | None = None  # send time of the last cycle still unanswered
        # pose mode: the last reply's planned pose (wire bytes) and its command
        self._last_command: tuple[bytes, np.ndarray | None] = (b"", None)
        self._sock, self._tx_stamps = _open_socket(
            bind_address or (net.controller_host, net.controller_port))

    # ------------------------------------------------------------------ the robot

    @property
    def q(self) -> np.ndarray:
        """Controller joints now (6,), deg."""
        return self.arm.q

    def tcp_pose(self) -> np.ndarray:
        """TCP pose (4x4, mm) of the current joints."""
        return self.arm.tcp_pose()

    @property
    def correction_mm(self) -> np.ndarray:
        """Pathcorr: the correction applied now (path frame, mm)."""
        return self.arm.corr.copy()

    def rest_at(self, q_deg: np.ndarray) -> None:
        """Put the robot at joints ``q_deg`` (6,) deg, at rest: the planned pose is the pose
        there and no target is pending (a closed-loop simulation starts a segment this way)."""
        self.arm.rest_at(q_deg)

    def _update(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance the arm by ``dt`` s; returns (feedback joints, feedback TCP, planned TCP) at
        the start of the step."""
        q_now, T_now, T_des, lag = self.arm.update(dt)
        with self._lock:
            self._stats.max_lag_mm = max(self._stats.max_lag_mm, lag)
        return q_now, T_now, T_des

    def _robot_message(self, q: np.ndarray, T: np.ndarray, T_plan: np.ndarray,
                       compute_s: float) -> Any:
        # the compiled cycle's quaternions and distance of these poses (None: computed there)
        self._messages.known = self.arm.last
        return self._messages.build(q, T, self.arm.q, T_plan, self.arm.running, compute_s)

    def _command(self, msg: Any) -> np.ndarray | None:
        """:func:`sensor_command` of a reply; in pose mode the same pose as the last reply's
        (its ``planned`` the same bytes: the sensor repeats its command every cycle until the
        next) gives the last reply's command again, unconverted (the same numbers, read-only)."""
        if self.mode != "pose":
            return sensor_command(msg, self.mode)
        key = msg.planned.SerializeToString()
        if key != self._last_command[0]:
            command = sensor_command(msg, self.mode)
            if command is not None:
                command.setflags(write=False)
            self._last_command = (key, command)
        return self._last_command[1]

    def _apply_reply(self, msg: Any) -> None:
        command = self._command(msg)
        if command is None:
            with self._lock:
                self._stats.rejected["zero_quaternion"] += 1
            return
        if self.mode == "pose":
            self.arm.target = command
        else:
            self.arm.corr_cmd = command
        with self._lock:
            self.received.append((time.monotonic(), msg))

    # ------------------------------------------------------------------ lockstep

    def step_lockstep(self, exchange: Callable[[bytes], bytes | None] | None) -> str:
        """One control cycle in lockstep with a simulation clock: no socket, no waiting.

        Moves the model by one period (as :meth:`run` does every tick); then, unless
        ``exchange`` is None (the controller is silent this cycle and sends nothing), stamps
        this cycle's ``EgmRobot`` and hands its wire bytes to ``exchange``, which returns the
        sensor's reply bytes, or None when the datagram or its reply was lost. A reply is
        validated and applied as one read from the socket would be.

        Args:
            exchange: ``bytes -> bytes | None``, the sensor side (e.g.
                :meth:`~torchseam.robot.egm.EgmLink.handle_datagram` with a sender address).

        Returns:
            "" when a valid reply was applied, else why not: ``"silent"``, ``"no_reply"`` or
            the reason the reply failed validation; ``"lost"`` when random packet loss
            (:meth:`set_loss`) took this cycle's ``EgmRobot``.
        """
        q, T, T_plan = self._update(self.period)
        with self._lock:
            self._stats.cycles += 1
        if exchange is None:
            return "silent"
        data = self._messages.stamp(self._robot_message(q, T, T_plan, 0.0))
        if self.faults.lost():
            with self._lock:
                self._stats.faults["loss"] += 1
            return "lost"  # on the way to the sensor: as a ``drop`` fault, nothing expected
        with self._lock:
            self._stats.sent += 1
            self._stats.expected += 1
        reply = exchange(data)
        if reply is None:
            return "no_reply"
        msg, why = parse_sensor(reply, self.mode, self._max_reply)
        if msg is None:
            with self._lock:
                self._stats.rejected[why] += 1
            return why
        with self._lock:
            self._stats.replies += 1
        self._apply_reply(msg)
        return ""

    # ------------------------------------------------------------------ faults

    def inject(self, fault: Fault | str, cycles: int = 1) -> None:
        """Apply ``fault`` (:class:`~torchseam.robot.sim_controller.faults.Fault`) to the next
        ``cycles`` cycles (queued after earlier injections)."""
        self.faults.inject(fault, cycles)

    def set_loss(self, fraction: float, mean_burst: float = 1.0, seed: int = 0) -> None:
        """Lose ``fraction`` of the cycles' ``EgmRobot`` on the way, in bursts of
        ``mean_burst`` cycles on average (a Gilbert-Elliott channel), from the next cycle on,
        until :meth:`clear_loss`, in lockstep and on the socket alike. A lost datagram counts
        as the fault ``loss`` (like ``drop``)."""
        self.faults.set_loss(fraction, mean_burst, seed)

    def clear_loss(self) -> None:
        """No more random packet loss."""
        self.faults.clear_loss()

    # ------------------------------------------------------------------ the wire

    def _tx_stamp(self) -> int | None:
        """The newest kernel transmit time stamp queued on the socket's error queue
        (CLOCK_REALTIME ns, as ``time.time_ns()``), or None (none queued, or not supported).
        Reads them all: a queued one would keep ``select`` waking."""
        if not self._tx_stamps:
            return None
        stamp = None
        while True:
            try:
                _, anc, _, _ = self._sock.recvmsg(1, 256, socket.MSG_ERRQUEUE)
            except OSError:  # empty (EAGAIN), or the socket is closed
                return stamp
            for level, kind, data in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPING and len(data) >= 16:
                    sec, nsec = TIMESPEC.unpack_from(data)  # [0]: the software stamp
                    stamp = sec * 1_000_000_000 + nsec

    def _send(self, data: bytes) -> int | None:
        """Send this cycle's datagram through the fault plan. Returns when the datagram that
        expects a reply left (kernel transmit time stamp, CLOCK_REALTIME ns; ``time.time_ns()``
        right before ``sendto`` where the kernel gives none), or None if none does."""
        out = self.faults.shape(data)
        if out.fault is not None:
            with self._lock:
                self._stats.faults[out.fault] += 1
        sent_ns = None
        for d in out.datagrams:
            try:
                # when it left is the kernel's transmit time stamp: this thread can be held
                # between its own clock reading and the wire (the GIL, the scheduler, a
                # hypervisor), and a request stamped before that would charge the hold to the
                # sensor. Without kernel stamps: the time right before sendto (on loopback the
                # reply can be heard before sendto returns, so never the time after it)
                before_ns = time.time_ns()
                self._sock.sendto(d, self.sensor_address)
                left_ns = self._tx_stamp()
                first_out = sent_ns is None
                if first_out:
                    sent_ns = before_ns if left_ns is None else left_ns
                with self._lock:
                    self._stats.sent += 1
                    self._stats.unstamped += int(first_out and out.expect and left_ns is None)
            except OSError as e:
                with self._lock:
                    self._stats.send_errors += 1
                    first = self._stats.send_errors == 1
                log.log(logging.WARNING if first else logging.DEBUG,
                        "simulated controller: sending to %s failed: %s", self.sensor_address, e)
        return sent_ns if out.expect else None

    # ------------------------------------------------------------------ loop

    def _receive_until(self, deadline: float, cycle_sent_ns: int | None,
                       answered: bool) -> bool:
        """Handle replies until ``deadline`` (perf_counter s); returns whether this cycle got
        its reply. The socket is drained once more at the deadline, so a reply that arrived in
        time counts even when this thread wakes up late (lateness is judged by the kernel's
        receive time stamp, not by when Python reads it)."""
        while True:
            answered = self._drain(cycle_sent_ns, answered)
            timeout = deadline - time.perf_counter()
            if timeout <= 0 or self._stop.is_set():
                return answered
            try:
                select.select([self._sock], [], [], timeout)
            except (OSError, ValueError):
                return answered

    def _credit(self, latency_ns: int, sent_ns: int) -> None:
        """A reply came ``latency_ns`` after its EgmRobot; later than a period is late.
        Call with the lock held."""
        self._stats.latency_ms.append(latency_ns / 1e6)
        if latency_ns > self.period * 1e9:
            self._stats.late_replies += 1
            self._stats.late_cycles_ns.append(sent_ns)

    def _close_pending(self) -> None:
        """The previous cycle's reply did not come before this cycle's EgmRobot: late.
        Call with the lock held."""
        if self._pending_ns is not None:
            self._stats.late_replies += 1
            self._stats.late_cycles_ns.append(self._pending_ns)
            self._pending_ns = None

    def _drain(self, cycle_sent_ns: int | None, answered: bool) -> bool:
        """Read every queued reply (non-blocking)."""
        self._tx_stamp()  # a stamp that came after its sendto returned: too late to use
        while True:
            try:
                data, anc, flags, _ = self._sock.recvmsg(self._max_reply + 1, 128)
            except (BlockingIOError, InterruptedError):
                return answered
            except OSError:  # closed by stop(), or ICMP port unreachable (no sensor yet)
                return answered
            rx_ns = rx_time_ns(anc)
            if flags & socket.MSG_TRUNC:
                msg, why = None, "oversized"
            else:
                msg, why = parse_sensor(data, self.mode, self._max_reply)
            with self._lock:
                if msg is None:
                    self._stats.rejected[why] += 1
                    continue
                self._stats.replies += 1
                pending = self._pending_ns
                if cycle_sent_ns is not None and not answered and rx_ns >= cycle_sent_ns:
                    self._credit(rx_ns - cycle_sent_ns, cycle_sent_ns)
                    answered = True
                elif pending is not None and pending <= rx_ns < (cycle_sent_ns or 1 << 63):
                    # sent before the next EgmRobot left, read after the cycle closed: it
                    # answers the previous cycle, late or not by its own time stamp
                    self._credit(rx_ns - pending, pending)
                    self._pending_ns = None
                else:  # a second reply to one EgmRobot
                    self._stats.extra_replies += 1
            self._apply_reply(msg)

    def run(self, duration_s: float | None = None,
            on_cycle: Callable[[SimController], None] | None = None) -> SimStats:
        """Run cycles in this thread for ``duration_s`` (None: until :meth:`stop`)."""
        n_cycles = None if duration_s is None else max(1, int(round(duration_s / self.period)))
        self.realtime = set_realtime_priority(self.sim.rt_priority, "simulated controller")
        t_next = time.perf_counter()
        sent_ns: int | None = None
        expect = answered = False
        msg = self._robot_message(*self._update(self.period), 0.0)
        k = 0
        while not self._stop.is_set() and (n_cycles is None or k < n_cycles):
            answered = self._receive_until(t_next, sent_ns if expect else None, answered)
            start = time.perf_counter()
            late_s = start - t_next
            with self._lock:
                # a reply is late when it comes more than a period after its EgmRobot left,
                # or not before the next one leaves; judged by time stamps, so that this
                # thread waking late does not shorten the sensor's window
                self._close_pending()
                if expect and not answered:
                    self._pending_ns = sent_ns
                self._stats.jitter_ms.append(late_s * 1e3)
                if late_s > self.period / 2:
                    self._stats.overruns += 1
            # send at the tick what the previous cycle prepared, then prepare the next one
            # while the sensor answers: the sensor gets the whole period, as on an IRC5
            sent_at, wall_at = time.perf_counter(), time.time_ns()
            stamp = self._send(self._messages.stamp(msg))
            expect = stamp is not None
            sent_ns = stamp if stamp is not None else time.time_ns()
            # when it left, on this loop's clock (held on its way out, it left later)
            sent_at += max(0, sent_ns - wall_at) / 1e9 if expect else 0.0
            with self._lock:
                self._stats.send_ms.append((sent_at - start) * 1e3)
            answered = False
            c0 = time.perf_counter()
            q, T, T_plan = self._update(self.period)
            compute = time.perf_counter() - c0
            msg = self._robot_message(q, T, T_plan, compute)
            with self._lock:
                self._stats.cycles += 1
                self._stats.compute_ms.append(compute * 1e3)
                if expect:
                    self._stats.expected += 1
            if on_cycle is not None:
                on_cycle(self)
            k += 1
            # never less than a period to the next EgmRobot: when this thread stalled between
            # its tick and the datagram leaving (or overran), the schedule moves. Sending the
            # next one early would close this cycle before its period is up (or leave the
            # sensor two back to back, one of them to skip): the simulator's fault, not the
            # sensor's
            t_next = max(t_next + self.period, sent_at + self.period)
        # the last cycle's reply window
        answered = self._receive_until(t_next, sent_ns if expect else None, answered)
        if not self._stop.is_set():
            with self._lock:
                self._close_pending()
                if expect and not answered:
                    self._pending_ns = sent_ns
                    self._close_pending()
        return self.stats

    def start(self, duration_s: float | None = None) -> SimController:
        """Run in a background thread (``duration_s`` None: until :meth:`stop`)."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self.run, args=(duration_s,),
                                            name="egm-sim-controller", daemon=True)
            self._thread.start()
        return self

    @property
    def running(self) -> bool:
        """True while the background thread runs."""
        return self._thread is not None and self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        """Wait for a ``start(duration_s)`` run to end."""
        if self._thread is not None:
            self._thread.join(timeout)

    def stop(self) -> None:
        """Stop the loop and close the socket (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._sock.close()

    def __enter__(self) -> SimController:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wait_cycles(self, n: int, timeout_s: float = 10.0) -> None:
        """Block until at least ``n`` cycles have run (raises ``TimeoutError``)."""
        end = time.monotonic() + timeout_s
        while self.cycles < n:
            if time.monotonic() > end:
                raise TimeoutError(f"simulated controller ran {self.cycles} of {n} "
                                   f"cycles in {timeout_s} s")
            time.sleep(0.002)

    @property
    def cycles(self) -> int:
        """Cycles run so far (cheaper than :attr:`stats`)."""
        with self._lock:
            return self._stats.cycles

    # ------------------------------------------------------------------ inspection

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` the controller sends from."""
        host, port = self._sock.getsockname()[:2]
        return host, port

    @property
    def stats(self) -> SimStats:
        with self._lock:
            return self._stats.copy()

    def replies(self) -> list[tuple[float, Any]]:
        """The recent valid replies, oldest first: ``(time.monotonic() s, message)``."""
        with self._lock:
            return list(self.received)


def _open_socket(bind_address: tuple[str, int]) -> tuple[socket.socket, bool]:
    """The controller's non-blocking UDP socket, bound, with kernel receive time stamps where
    the kernel gives them; and whether it stamps each datagram as it leaves."""
    sock = open_udp(bind_address, "the simulated controller")
    tx_stamps = False
    if _SO_TIMESTAMPING is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPING, _TX_STAMP_FLAGS)
            tx_stamps = True
        except OSError:
            pass
    return sock, tx_stamps
