"""A simulated IRC5 controller that speaks EGM on loopback, with the IRB 1410 model.

Every cycle (``sim_controller.rate_hz``, 250 Hz = 4 ms by default) it sends an ``EgmRobot`` to
the sensor: feedback joints and TCP pose (forward kinematics of
:class:`~torchseam.robot.kinematics.IRB1410` and the cell's tool), the planned joints and pose,
motor / MCI / RAPID state, the wall clock, and its utilisation. Between cycles it waits for the
sensor's replies and moves the robot:

- ``mode: pose`` (``EgmSensor``): the planned TCP pose moves towards the latest received target
  at ``tcp_speed_mm_s`` / ``tcp_rot_speed_deg_s``.
- ``mode: pathcorr`` (``EgmSensorPathCorr``): the robot runs a programmed path (TCP poses,
  default a straight line from the home pose, ``path_direction`` / ``path_length_mm``) at
  ``path_speed_mm_s``; the received offset, given in the nominal TCP frame (the "sensor tool"
  frame of ``EGMActMove``), is applied at most ``correction_speed_mm_s`` fast.

In both modes the joints follow the planned pose by one damped Newton step per cycle on the
model's numerical Jacobian (the planned pose moves ~1 mm a cycle at most, so one step
converges), all axes scaled together so none exceeds its speed limit. Not ``robot.ik`` on every
new target: its torch overhead per solve is a large part of the 4 ms cycle, which then overruns
and sends datagrams back to back; the model's IK still finds the start joints of a
programmed path that does not begin at the home pose. Forward kinematics runs in closed form
(numpy) from the model's own arm geometry, checked against ``robot.fk`` at start-up.

Each cycle sends, right at its tick, the ``EgmRobot`` prepared during the previous cycle and
then prepares the next one, so the sensor has the whole period to answer; the feedback is thus
one cycle old, as on a real controller. Replies are matched to cycles: the first valid reply
that arrives before the next ``EgmRobot`` leaves gives a latency sample (kernel time stamps on
both ends); a reply more than one period after its ``EgmRobot``, or none before the next one
leaves, is a late reply.

Fault injection for tests (:meth:`SimController.inject`, applied to the next N cycles):
``drop`` (send nothing), ``duplicate`` (send twice), ``reorder`` (hold back, send after the
next cycle's datagram: N reorders in a row all arrive after the N+1th), ``corrupt`` (flip
bytes and cut the tail), ``oversized`` (pad past the sensor's limit with an unknown field) and
``silence`` (send nothing; the controller has stopped). :meth:`SimController.set_loss` adds
random packet loss: a fraction of the cycles' ``EgmRobot`` lost on the way, in bursts
(:class:`BurstLoss`, a Gilbert-Elliott channel), in lockstep and on the socket alike.

Everything is bounded: receive buffers, sample deques, and the wait per cycle.
"""

from __future__ import annotations

import collections
import enum
import logging
import math
import select
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from torchseam.core.config import load_cell
from torchseam.core.transforms import matrix_to_quat, quat_to_matrix, rotvec
from torchseam.robot.egm import (
    SO_TIMESTAMPNS,
    TIMESPEC,
    EgmError,
    copy_stats,
    latency_summary,
    parse_sensor,
    rx_time_ns,
    set_realtime_priority,
)
from torchseam.robot.egm.config import EgmConfig, load_egm_config
from torchseam.robot.egm.messages import (
    EgmHeader,
    EgmMCIState,
    EgmMotorState,
    EgmRapidCtrlExecState,
    EgmRobot,
)

log = logging.getLogger("torchseam.robot.sim_controller")

_U32 = 0xFFFFFFFF
_H_DEG = 1e-4          # finite-difference step of the Jacobian, deg
_ROT_WEIGHT = 200.0    # mm per rad: makes orientation and position errors comparable
_DAMPING = 1e-3        # damped least squares, keeps the step bounded near singularities
_CONVERGED_MM = 0.05   # |planned - feedback| below this: mciConvergenceMet
# kernel transmit time stamps (Linux, Documentation/networking/timestamping.rst): a software
# stamp as each datagram leaves, reported on the error queue without the payload
_SO_TIMESTAMPING = getattr(socket, "SO_TIMESTAMPING", 37) if sys.platform == "linux" else None
_TX_STAMP_FLAGS = (1 << 1) | (1 << 4) | (1 << 11)  # TX_SOFTWARE | SOFTWARE | OPT_TSONLY


class Fault(str, enum.Enum):
    """Faults :meth:`SimController.inject` can put on the wire."""

    DROP = "drop"
    DUPLICATE = "duplicate"
    REORDER = "reorder"
    CORRUPT = "corrupt"
    OVERSIZED = "oversized"
    SILENCE = "silence"


class BurstLoss:
    """Packet loss in bursts (a Gilbert-Elliott channel): a good state that loses nothing and a
    bad state that loses every datagram. Each cycle the channel goes bad with probability
    ``p`` and back to good with ``r``: bursts last ``1 / r`` cycles on average and the long-run
    loss is ``p / (p + r)``.

    Args:
        fraction: long-run fraction of cycles lost, in [0, 1).
        mean_burst: mean burst length, cycles (>= 1).
        seed: seed of the channel's random draws (the same seed loses the same cycles).

    Example:
        >>> ch = BurstLoss(0.1, 4.0, seed=1)
        >>> lost = [ch.lose() for _ in range(100_000)]
        >>> round(sum(lost) / len(lost), 2)
        0.1
    """

    def __init__(self, fraction: float, mean_burst: float, seed: int = 0) -> None:
        if not (0.0 <= fraction < 1.0) or not mean_burst >= 1.0:
            raise ValueError(f"loss fraction must lie in [0, 1) and the mean burst be >= 1 "
                             f"cycle, got {fraction!r}, {mean_burst!r}")
        self.fraction, self.mean_burst = float(fraction), float(mean_burst)
        self.r = 1.0 / self.mean_burst                      # bad -> good
        self.p = self.fraction * self.r / (1.0 - self.fraction)  # good -> bad
        self._rng = np.random.default_rng(seed)
        self.bad = False
        self.lost = 0
        self.cycles = 0
        self.bursts = 0

    def lose(self) -> bool:
        """Advance one cycle; True when this cycle's datagram is lost."""
        u = float(self._rng.random())
        if self.bad:
            self.bad = u >= self.r
        else:
            self.bad = u < self.p
            self.bursts += int(self.bad)
        self.cycles += 1
        self.lost += int(self.bad)
        return self.bad


@dataclass
class SimStats:
    """Counters of the simulated controller.

    Attributes:
        cycles: control cycles run.
        sent: ``EgmRobot`` datagrams put on the wire (faulty ones included).
        expected: cycles that sent a valid, in-order ``EgmRobot`` and so expect a reply.
        replies: valid replies received.
        late_replies: expecting cycles whose reply came more than one period after their
            ``EgmRobot`` left (kernel time stamps), or not before the next one left.
        extra_replies: valid replies beyond the first to one ``EgmRobot``.
        rejected: replies that failed validation, by reason.
        faults: injected faults, by kind.
        send_errors: datagrams the socket refused to send.
        unstamped: expecting ``EgmRobot`` without a kernel transmit time stamp, timed from
            the clock right before ``sendto`` instead (a hold there counts against the sensor).
        max_lag_mm: largest distance between the planned and the fed-back TCP position.
        overruns: cycles that started more than half a period late (the schedule then
            moves: the next ``EgmRobot`` never leaves less than a period after the previous
            one).
        latency_ms: ``EgmRobot`` leaving to the reply arriving (kernel time stamps on both
            ends where the kernel gives them), ms (late replies
            included when they arrive during the next cycle).
        jitter_ms: cycle start minus its scheduled time, ms.
        send_ms: cycle start to its ``EgmRobot`` leaving (kernel transmit time stamp), ms:
            where this controller, not the sensor, held a cycle up.
        compute_ms: model update time per cycle, ms.
        late_cycles_ns: when (``time.time_ns()``) each cycle that got no reply in time sent
            its ``EgmRobot``; lets a test line late replies up with machine stalls.
    """

    cycles: int = 0
    sent: int = 0
    expected: int = 0
    replies: int = 0
    late_replies: int = 0
    extra_replies: int = 0
    rejected: collections.Counter[str] = field(default_factory=collections.Counter)
    faults: collections.Counter[str] = field(default_factory=collections.Counter)
    send_errors: int = 0
    unstamped: int = 0
    max_lag_mm: float = 0.0
    overruns: int = 0
    latency_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    jitter_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    send_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    compute_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    late_cycles_ns: collections.deque[int] = field(
        default_factory=lambda: collections.deque(maxlen=10_000))

    def copy(self) -> SimStats:
        return copy_stats(self)

    def as_dict(self) -> dict[str, Any]:
        return {"cycles": self.cycles, "sent": self.sent, "expected": self.expected,
                "replies": self.replies, "late_replies": self.late_replies,
                "extra_replies": self.extra_replies, "rejected": dict(self.rejected),
                "faults": dict(self.faults), "send_errors": self.send_errors,
                "unstamped": self.unstamped,
                "max_lag_mm": self.max_lag_mm,
                "overruns": self.overruns, "latency_ms": latency_summary(self.latency_ms),
                "jitter_ms": latency_summary(np.abs(np.fromiter(self.jitter_ms, float))),
                "send_ms": latency_summary(self.send_ms),
                "compute_ms": latency_summary(self.compute_ms)}


def straight_path(start: np.ndarray, direction: np.ndarray, length_mm: float,
                  step_mm: float = 5.0) -> np.ndarray:
    """TCP poses (N, 4, 4) along a straight line from ``start`` (4x4, mm), same orientation."""
    n = max(2, int(math.ceil(length_mm / step_mm)) + 1)
    s = np.linspace(0.0, length_mm, n)
    path = np.repeat(start[None], n, axis=0)
    path[:, :3, 3] = start[:3, 3] + s[:, None] * np.asarray(direction, float)[None]
    return path


class _Path:
    """Arc-length parametrised TCP path: positions piecewise linear, orientations slerped."""

    def __init__(self, poses: np.ndarray) -> None:
        poses = np.asarray(poses, dtype=float)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) < 2:
            raise EgmError(f"a programmed path needs >= 2 poses of shape (4, 4), got "
                           f"{poses.shape}")
        seg = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        if not np.all(seg > 0):
            raise EgmError("a programmed path must not repeat a position")
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.s[-1])
        self.pos = poses[:, :3, 3].copy()
        quats = matrix_to_quat(poses[:, :3, :3])
        for i in range(1, len(quats)):  # one hemisphere, so slerp takes the short way
            if np.dot(quats[i], quats[i - 1]) < 0:
                quats[i] = -quats[i]
        self.quat = quats

    def at(self, s: float) -> np.ndarray:
        """TCP pose (4x4, mm) at arc length ``s`` (clamped to the path)."""
        s = min(max(s, 0.0), self.length)
        i = min(int(np.searchsorted(self.s, s, side="right")) - 1, len(self.s) - 2)
        u = (s - self.s[i]) / (self.s[i + 1] - self.s[i])
        T = np.eye(4)
        T[:3, 3] = self.pos[i] + u * (self.pos[i + 1] - self.pos[i])
        T[:3, :3] = quat_to_matrix(_slerp(self.quat[i], self.quat[i + 1], u))
        return T


class SimController:
    """Simulated IRC5 EGM endpoint (see the module docstring).

    Args:
        config: EGM configuration (default ``configs/egm.yaml``).
        sensor_address: where to send ``EgmRobot`` (default ``network.host:network.port``).
        bind_address: the controller's own address (default ``network.controller_host`` and
            ``network.controller_port``; port 0 binds an ephemeral one, see :attr:`address`).
        mode: ``pose`` or ``pathcorr`` (default the config's).
        robot: the kinematic model (default :class:`~torchseam.robot.kinematics.IRB1410`).
        tool: TCP pose in the flange frame, 4x4 mm (default the cell's torch).
        path: programmed TCP path for pathcorr, (N, 4, 4) mm in the base frame (default a
            straight line from the home pose along ``path_direction``).
        seed: seed of the ``corrupt`` fault's byte flips.
    """

    def __init__(self, config: EgmConfig | None = None, *,
                 sensor_address: tuple[str, int] | None = None,
                 bind_address: tuple[str, int] | None = None,
                 mode: str | None = None, robot: Any = None, tool: np.ndarray | None = None,
                 path: np.ndarray | None = None, seed: int = 0) -> None:
        from torchseam.robot.kinematics import IRB1410

        self.config = config or load_egm_config()
        net = self.config.network
        self.sim = self.config.sim_controller
        self.mode = mode or self.config.mode
        if self.mode not in ("pose", "pathcorr"):
            raise EgmError(f"mode must be pose or pathcorr, got {self.mode!r}")
        self.sensor_address = sensor_address or (net.host, net.port)
        self.robot = robot if robot is not None else IRB1410()
        self.tool = np.asarray(tool if tool is not None else load_cell().tool.matrix(), float)
        self.period = self.sim.period_s
        self._speed = np.asarray(self.sim.joint_speed_deg_s, float)
        self._rng = np.random.default_rng(seed)
        self._max_reply = self.config.link.max_datagram_bytes
        self._oversize = 2 * self.config.link.max_datagram_bytes

        self._fast_fk = self._pick_fk()
        self.q = np.asarray(self.sim.home_joints_deg, float).copy()
        start = self._fk(self.q[None])[0]
        if path is None:
            path = straight_path(start, np.asarray(self.sim.path_direction),
                                 max(self.sim.path_length_mm, 1.0))
        self.path = _Path(path)
        if self.mode == "pathcorr" and not np.allclose(self.path.at(0.0), start, atol=1e-3):
            q0 = self._ik(self.path.at(0.0), self.q)  # start where the program starts
            if q0 is None:
                raise EgmError("the programmed path's first pose is out of the robot's reach")
            self.q = q0
        self._s = 0.0                      # arc length run so far, mm
        self._corr_cmd = np.zeros(3)       # last received correction, mm (path frame)
        self._corr = np.zeros(3)           # correction applied (rate-limited), mm
        self._target: np.ndarray | None = None   # pose mode: latest received TCP target
        self._planned = self._fk(self.q[None])[0]

        self._faults: collections.deque[Fault] = collections.deque(maxlen=100_000)
        self._held: list[bytes] = []       # datagrams held back by reorder faults
        self.loss: BurstLoss | None = None  # random packet loss (set_loss), None: none
        self._lock = threading.Lock()
        self._stats = SimStats()
        self._seqno = 0
        self._t0 = time.perf_counter()
        # recent valid replies as (monotonic s, message), for tests and demos
        self.received: collections.deque[tuple[float, Any]] = collections.deque(maxlen=1024)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.realtime = False  # whether the cycle thread got its real-time priority
        self._pending_ns: int | None = None  # send time of the last cycle still unanswered
        self._sock = socket.socket(socket.AF_INET6 if ":" in (bind_address or (
            net.controller_host,))[0] else socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(bind_address or (net.controller_host, net.controller_port))
        except OSError as e:
            self._sock.close()
            raise EgmError(f"cannot bind the simulated controller to "
                           f"{bind_address or (net.controller_host, net.controller_port)}: "
                           f"{e.strerror or e}") from None
        self._sock.setblocking(False)
        if SO_TIMESTAMPNS is not None:
            try:
                self._sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            except OSError:
                pass
        self._tx_stamps = False  # whether the kernel stamps each datagram as it leaves
        if _SO_TIMESTAMPING is not None:
            try:
                self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPING, _TX_STAMP_FLAGS)
                self._tx_stamps = True
            except OSError:
                pass

    # ------------------------------------------------------------------ kinematics

    def _fk(self, q: np.ndarray) -> np.ndarray:
        """TCP poses (N, 4, 4) mm for controller joints (N, 6) deg."""
        if self._fast_fk is not None:
            return self._fast_fk(q) @ self.tool
        with torch.no_grad():
            T = self.robot.fk(torch.as_tensor(q, dtype=torch.float64)).numpy()
        return T @ self.tool

    def _pick_fk(self) -> Callable[[np.ndarray], np.ndarray] | None:
        """The model's FK in closed form (numpy), if the model exposes its arm geometry and the
        closed form agrees with ``robot.fk`` to 1e-6 mm on random joints; else None.

        Why: pytorch-kinematics' Python and tensor overhead on one pose is a large part of
        the 4 ms cycle; the same numbers in numpy cost a fraction of that for all 7 poses of a
        numerical Jacobian, leaving the CPU to the sensor that is being tested.
        """
        geometry = getattr(self.robot, "geometry", None)
        if geometry is None:
            return None

        def fk(q: np.ndarray) -> np.ndarray:
            return _closed_form_fk(q, geometry)

        q = np.random.default_rng(1).uniform(-1.0, 1.0, (64, 6)) * [170, 70, 65, 150, 115, 300]
        try:
            with torch.no_grad():
                ref = self.robot.fk(torch.as_tensor(q, dtype=torch.float64)).numpy()
            err = float(np.abs(fk(q) - ref).max())
        except Exception as e:  # a model without this geometry layout
            log.info("simulated controller: closed-form FK unusable (%s), using robot.fk", e)
            return None
        if not err < 1e-6:
            log.info("simulated controller: closed-form FK differs from robot.fk by %.3g mm, "
                     "using robot.fk", err)
            return None
        return fk

    def _ik(self, T_tcp: np.ndarray, seed: np.ndarray) -> np.ndarray | None:
        """Controller joints for a TCP pose, or None when unreachable."""
        T_flange = T_tcp @ np.linalg.inv(self.tool)
        with torch.no_grad():
            q, ok = self.robot.ik(torch.as_tensor(T_flange[None], dtype=torch.float64),
                                  torch.as_tensor(seed[None], dtype=torch.float64))
        if not bool(ok[0]):
            return None
        return q[0].numpy().astype(float)

    def _newton_step(self, T_des: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One damped Newton step towards ``T_des``: (joint step deg, TCP pose now)."""
        qs = np.repeat(self.q[None], 7, axis=0)
        qs[1:] += np.eye(6) * _H_DEG
        T = self._fk(qs)
        T0 = T[0]
        R0t = T0[:3, :3].T
        J = np.empty((6, 6))
        J[:3] = ((T[1:, :3, 3] - T0[:3, 3]) / _H_DEG).T
        J[3:] = (rotvec(T[1:, :3, :3] @ R0t) * (_ROT_WEIGHT / _H_DEG)).T
        err = np.concatenate([T_des[:3, 3] - T0[:3, 3],
                              rotvec(T_des[:3, :3] @ R0t) * _ROT_WEIGHT])
        dq = np.linalg.solve(J.T @ J + _DAMPING * np.eye(6), J.T @ err)
        return dq, T0

    def _limit(self, dq: np.ndarray, dt: float) -> np.ndarray:
        """Scale a joint step so that no axis exceeds its speed limit (path shape kept)."""
        over = float(np.max(np.abs(dq) / (self._speed * dt)))
        return dq / over if over > 1.0 else dq

    def _update(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance the model by ``dt`` s; returns (feedback joints, feedback TCP, planned TCP)
        at the start of the step."""
        q_now = self.q.copy()
        if self.mode == "pathcorr":
            self._s = min(self._s + self.sim.path_speed_mm_s * dt, self.path.length)
            dc = self._corr_cmd - self._corr
            max_dc = self.sim.correction_speed_mm_s * dt
            n = float(np.linalg.norm(dc))
            self._corr = self._corr + (dc if n <= max_dc else dc * (max_dc / n))
            T_des = self.path.at(self._s)
            T_des[:3, 3] += T_des[:3, :3] @ self._corr
        elif self._target is not None:
            T_des = _step_towards(self._planned, self._target, self.sim.tcp_speed_mm_s * dt,
                                  math.radians(self.sim.tcp_rot_speed_deg_s) * dt)
        else:
            T_des = self._planned
        dq, T_now = self._newton_step(T_des)
        self.q = self.q + self._limit(dq, dt)
        self._planned = T_des
        lag = float(np.linalg.norm(T_des[:3, 3] - T_now[:3, 3]))
        with self._lock:
            self._stats.max_lag_mm = max(self._stats.max_lag_mm, lag)
        return q_now, T_now, T_des

    # ------------------------------------------------------------------ messages

    def _robot_message(self, q: np.ndarray, T: np.ndarray, T_plan: np.ndarray,
                       compute_s: float) -> Any:
        """The next ``EgmRobot`` (header and clocks are stamped when it is sent)."""
        msg = EgmRobot()
        for part, joints, pose in ((msg.feedBack, q, T), (msg.planned, self.q, T_plan)):
            part.joints.joints.extend(float(x) for x in joints)
            _fill_pose(part.cartesian, pose)
        msg.motorState.state = EgmMotorState.MOTORS_ON
        msg.mciState.state = EgmMCIState.MCI_RUNNING
        msg.mciConvergenceMet = bool(np.linalg.norm(T[:3, 3] - T_plan[:3, 3]) < _CONVERGED_MM)
        running = self.mode == "pose" or self._s < self.path.length
        msg.rapidExecState.state = (EgmRapidCtrlExecState.RAPID_RUNNING if running
                                    else EgmRapidCtrlExecState.RAPID_STOPPED)
        msg.utilizationRate = 100.0 * compute_s / self.period
        return msg

    def _stamp(self, msg: Any) -> bytes:
        """Sequence number, controller time (ms) and wall clock, then the wire bytes."""
        self._seqno = (self._seqno + 1) & _U32
        h = msg.header
        h.seqno = self._seqno
        h.tm = int((time.perf_counter() - self._t0) * 1e3) & _U32
        h.mtype = EgmHeader.MSGTYPE_DATA
        now = time.time()
        for part in (msg.feedBack, msg.planned):
            part.time.sec = int(now)
            part.time.usec = int((now % 1.0) * 1e6)
        return msg.SerializeToString()

    def _apply_reply(self, msg: Any) -> None:
        if self.mode == "pose":
            c = msg.planned.cartesian
            if c.HasField("euler"):  # EGM: Euler angles win over the quaternion
                e = c.euler
                R = Rotation.from_euler("ZYX", [e.z, e.y, e.x], degrees=True).as_matrix()
            else:
                o = c.orient
                q = np.array([o.u0, o.u1, o.u2, o.u3])
                n = float(np.linalg.norm(q))
                if not n > 0.0:
                    with self._lock:
                        self._stats.rejected["zero_quaternion"] += 1
                    return
                R = quat_to_matrix(q / n)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = [c.pos.x, c.pos.y, c.pos.z]
            self._target = T
        else:
            p = msg.pathCorr.pos
            self._corr_cmd = np.array([p.x, p.y, p.z])
        with self._lock:
            self.received.append((time.monotonic(), msg))

    # ------------------------------------------------------------------ lockstep

    def rest_at(self, q_deg: np.ndarray) -> None:
        """Put the robot at joints ``q_deg`` (6,) deg, at rest: the planned pose is the pose
        there and no target is pending (a closed-loop simulation starts a segment this way)."""
        q = np.asarray(q_deg, dtype=float).reshape(-1)
        if q.shape != (6,) or not np.isfinite(q).all():
            raise EgmError(f"rest_at needs 6 finite joint angles, got {q_deg!r}")
        self.q = q.copy()
        self._planned = self._fk(self.q[None])[0]
        self._target = None

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
        data = self._stamp(self._robot_message(q, T, T_plan, 0.0))
        if self._lost():
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
        """Apply ``fault`` to the next ``cycles`` cycles (queued after earlier injections)."""
        kind = Fault(fault)
        if cycles < 0:
            raise ValueError(f"cycles must be >= 0, got {cycles}")
        with self._lock:
            self._faults.extend([kind] * cycles)

    def set_loss(self, fraction: float, mean_burst: float = 1.0, seed: int = 0) -> None:
        """Lose ``fraction`` of the cycles' ``EgmRobot`` on the way, in bursts of
        ``mean_burst`` cycles on average (:class:`BurstLoss`), from the next cycle on, until
        :meth:`clear_loss`. A lost datagram counts as the fault ``loss`` (like ``drop``)."""
        self.loss = BurstLoss(fraction, mean_burst, seed) if fraction > 0 else None

    def clear_loss(self) -> None:
        """No more random packet loss."""
        self.loss = None

    def _lost(self) -> bool:
        """Whether random packet loss takes this cycle's datagram (counted)."""
        if self.loss is None or not self.loss.lose():
            return False
        with self._lock:
            self._stats.faults["loss"] += 1
        return True

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
        with self._lock:
            fault = self._faults.popleft() if self._faults else None
            if fault is not None:
                self._stats.faults[fault.value] += 1
        out: list[bytes] = []
        expect = False
        if fault in (Fault.DROP, Fault.SILENCE) or (fault is None and self._lost()):
            pass
        elif fault is Fault.DUPLICATE:
            out, expect = [data, data], True
        elif fault is Fault.REORDER:
            self._held.append(data)  # goes out after the next non-reordered cycle's datagram
        elif fault is Fault.CORRUPT:
            buf = bytearray(data)
            for i in self._rng.choice(len(buf), size=max(1, len(buf) // 16), replace=False):
                buf[i] ^= int(self._rng.integers(1, 256))
            out = [bytes(buf[:-1])]  # cutting the last byte truncates utilizationRate
        elif fault is Fault.OVERSIZED:
            pad = self._oversize - len(data)
            # an unknown length-delimited field 15: valid protobuf, just too large
            out = [data + bytes([0x7A]) + _varint(pad) + b"\0" * pad]
        else:
            out, expect = [data], True
        if self._held and fault is not Fault.REORDER:
            out += self._held
            self._held = []
        sent_ns = None
        for d in out:
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
                    self._stats.unstamped += int(first_out and expect and left_ns is None)
            except OSError as e:
                with self._lock:
                    self._stats.send_errors += 1
                    first = self._stats.send_errors == 1
                log.log(logging.WARNING if first else logging.DEBUG,
                        "simulated controller: sending to %s failed: %s", self.sensor_address, e)
        return sent_ns if expect else None

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
            stamp = self._send(self._stamp(msg))
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

    @property
    def correction_mm(self) -> np.ndarray:
        """Pathcorr: the correction applied now (path frame, mm)."""
        return self._corr.copy()

    def tcp_pose(self) -> np.ndarray:
        """TCP pose (4x4, mm) of the current joints."""
        return self._fk(self.q[None])[0]


def _fill_pose(pose: Any, T: np.ndarray) -> None:
    """Position (mm), quaternion (w, x, y, z) and ABB EulerZYX angles (deg) of a 4x4 pose."""
    pose.pos.x, pose.pos.y, pose.pos.z = (float(v) for v in T[:3, 3])
    q = matrix_to_quat(T[:3, :3])
    pose.orient.u0, pose.orient.u1, pose.orient.u2, pose.orient.u3 = (float(v) for v in q)
    R = T[:3, :3]
    # R = Rz(z) Ry(y) Rx(x) (ABB EulerZYX); plain math: scipy objects cost more per cycle
    pose.euler.y = math.degrees(math.asin(max(-1.0, min(1.0, -float(R[2, 0])))))
    pose.euler.z = math.degrees(math.atan2(float(R[1, 0]), float(R[0, 0])))
    pose.euler.x = math.degrees(math.atan2(float(R[2, 1]), float(R[2, 2])))


def _step_towards(T: np.ndarray, target: np.ndarray, max_mm: float,
                  max_rad: float) -> np.ndarray:
    """Pose moved from ``T`` towards ``target`` by at most ``max_mm`` and ``max_rad``."""
    out = np.eye(4)
    d = target[:3, 3] - T[:3, 3]
    n = float(np.linalg.norm(d))
    out[:3, 3] = target[:3, 3] if n <= max_mm else T[:3, 3] + d * (max_mm / n)
    q0, q1 = matrix_to_quat(T[:3, :3]), matrix_to_quat(target[:3, :3])
    if np.dot(q0, q1) < 0:
        q1 = -q1
    ang = 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))
    u = 1.0 if ang <= max_rad else max_rad / ang
    out[:3, :3] = quat_to_matrix(_slerp(q0, q1, u))
    return out


def _closed_form_fk(q_deg: np.ndarray, g: Any) -> np.ndarray:
    """Flange poses (N, 4, 4) mm of an IRB 1410-like arm from its geometry (``a1, d1, a2, a3,
    d4, d6`` mm, ``R0`` the flange rotation at zero), controller joints (N, 6) deg.

    Axis 1 about z; axis 2 tilts the lower arm about y; the controller's axis 3 is the forearm
    angle itself (parallelogram); the wrist turns x, y, x.
    """
    q = np.radians(np.asarray(q_deg, dtype=float).reshape(-1, 6))
    c, s = np.cos(q), np.sin(q)
    n = q.shape[0]

    def rot(i: int, axis: int) -> np.ndarray:
        a, b = [(1, 2), (2, 0), (0, 1)][axis]  # the plane the rotation turns
        R = np.zeros((n, 3, 3))
        R[:, axis, axis] = 1.0
        R[:, a, a] = R[:, b, b] = c[:, i]
        R[:, a, b] = -s[:, i]
        R[:, b, a] = s[:, i]
        return R

    R1 = rot(0, 2)
    R2 = R1 @ rot(1, 1)
    R3 = R1 @ rot(2, 1)
    R5 = R3 @ rot(3, 0) @ rot(4, 1)
    R6 = R5 @ rot(5, 0)
    p3 = R1 @ np.array([g.a1, 0.0, g.d1]) + R2 @ np.array([0.0, 0.0, g.a2])
    pw = p3 + R3 @ np.array([g.d4, 0.0, g.a3])
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = R6 @ np.asarray(g.R0, dtype=float)
    T[:, :3, 3] = pw + g.d6 * R5[:, :, 0]
    T[:, 3, 3] = 1.0
    return T


# (rotation helpers: torchseam.core.transforms)

def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions in one hemisphere."""
    d = min(1.0, float(np.dot(q0, q1)))
    if d > 0.9995:  # nearly equal: linear is exact enough and avoids 0/0
        q = q0 + u * (q1 - q0)
    else:
        a = math.acos(d)
        q = (math.sin((1 - u) * a) * q0 + math.sin(u * a) * q1) / math.sin(a)
    return q / np.linalg.norm(q)


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


__all__ = ["Fault", "SimController", "SimStats", "straight_path"]
