"""The simulated IRC5's arm: joints that follow a planned TCP pose, within the speed limits.

``pose`` mode moves the planned pose towards the latest target at the configured TCP speeds;
``pathcorr`` runs a programmed path (:class:`ProgrammedPath`) at the path speed and adds the
received correction, rate-limited, in the nominal TCP frame (the "sensor tool" frame of
``EGMActMove``). In both the joints follow the planned pose by one damped Newton step per cycle
on the analytic TCP Jacobian (:func:`~torchseam.robot.kinematics.arm_forward` with the tool;
the planned pose moves about 1 mm a cycle at most, so one step converges), all axes scaled
together so that none exceeds its speed limit.

Forward kinematics and the Jacobian are the kinematics module's closed form on its numpy path:
one source of truth with :meth:`~torchseam.robot.kinematics.IRB1410.fk`, and no torch overhead
in the 4 ms cycle. The model's (torch) IK runs only when a programmed path does not begin at the
home pose, once, to find its start joints.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from torchseam.core.kernels import load_kernels
from torchseam.core.transforms import matrix_to_quat, quat_to_matrix, slerp
from torchseam.robot.egm import EgmError, SimControllerConfig
from torchseam.robot.kinematics import arm_forward

_ROT_WEIGHT = 200.0    # mm per rad: makes orientation and position errors comparable
_DAMPING = 1e-3        # damped least squares, keeps the step bounded near singularities


def straight_path(start: np.ndarray, direction: np.ndarray, length_mm: float,
                  step_mm: float = 5.0) -> np.ndarray:
    """TCP poses (N, 4, 4) along a straight line from ``start`` (4x4, mm), same orientation."""
    n = max(2, int(math.ceil(length_mm / step_mm)) + 1)
    s = np.linspace(0.0, length_mm, n)
    path = np.repeat(start[None], n, axis=0)
    path[:, :3, 3] = start[:3, 3] + s[:, None] * np.asarray(direction, float)[None]
    return path


class ProgrammedPath:
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
        T[:3, :3] = quat_to_matrix(slerp(self.quat[i], self.quat[i + 1], u))
        return T


class QuatCache:
    """:func:`~torchseam.core.transforms.matrix_to_quat` of the few rotations a cycle meets
    again: the planned pose is converted by the cycle that plans it (its ``EgmRobot``) and by
    the next (:func:`step_towards`), the target by every cycle until the next command, and a
    robot at rest feeds back the same pose. A rotation is looked up by its bytes, so a hit
    returns the quaternion its own conversion gave (the same numbers); the quaternions are
    read-only. Bounded: a few entries."""

    SIZE = 8

    def __init__(self) -> None:
        self._quats: dict[bytes, np.ndarray] = {}

    def __call__(self, R: np.ndarray) -> np.ndarray:
        """The quaternion (w, x, y, z) of the (3, 3) rotation ``R``, w >= 0."""
        key = np.ascontiguousarray(R, dtype=float).tobytes()
        q = self._quats.get(key)
        if q is None:
            if len(self._quats) >= self.SIZE:
                self._quats.pop(next(iter(self._quats)))  # the oldest entry
            q = self._quats[key] = matrix_to_quat(R)
            q.setflags(write=False)
        return q


def step_towards(T: np.ndarray, target: np.ndarray, max_mm: float,
                 max_rad: float, quat=matrix_to_quat) -> np.ndarray:
    """Pose moved from ``T`` towards ``target`` by at most ``max_mm`` and ``max_rad``.
    ``quat``: the rotation -> quaternion conversion (a :class:`QuatCache`: the same numbers)."""
    out = np.eye(4)
    d = target[:3, 3] - T[:3, 3]
    n = float(np.linalg.norm(d))
    out[:3, 3] = target[:3, 3] if n <= max_mm else T[:3, 3] + d * (max_mm / n)
    q0, q1 = quat(T[:3, :3]), quat(target[:3, :3])
    ang = 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))
    u = 1.0 if ang <= max_rad else max_rad / ang
    out[:3, :3] = quat_to_matrix(slerp(q0, q1, u))
    return out


class ArmModel:
    """The simulated robot: joints, the planned TCP pose and what moves it (see the module
    docstring). Not thread-safe: one thread steps it; others may read :meth:`tcp_pose`.

    Args:
        robot: the kinematic model, an :class:`~torchseam.robot.kinematics.IRB1410` (its
            closed-form ``geometry`` and, for a path that starts away from home, its ``ik``).
        tool: TCP pose in the flange frame, 4x4 mm.
        sim: the simulated controller's settings (home joints, speeds, default path).
        mode: ``pose`` or ``pathcorr``.
        path: programmed TCP path for pathcorr, (N, 4, 4) mm in the base frame (default a
            straight line from the home pose along ``sim.path_direction``).

    Raises:
        EgmError: a bad path, or one whose first pose is out of reach.
    """

    def __init__(self, robot: Any, tool: np.ndarray, sim: SimControllerConfig, mode: str,
                 path: np.ndarray | None = None) -> None:
        self.robot = robot
        self.tool = np.ascontiguousarray(tool, dtype=float)
        self.sim = sim
        self.mode = mode
        self._geometry = g = robot.geometry
        self._g = np.array([g.a1, g.d1, g.a2, g.a3, g.d4, g.d6], dtype=float)
        self._R0 = np.ascontiguousarray(g.R0, dtype=float)
        kernels = load_kernels(__package__)
        self._kernel = kernels.newton_step
        self._speed = np.ascontiguousarray(sim.joint_speed_deg_s, dtype=float)
        # pose mode: the whole cycle compiled (``_kernels.pose_update``), where it computes
        # what the numpy statement below does to the bit on this machine (_pose_kernel_agrees)
        compiled = mode == "pose" and _pose_kernel_agrees(robot, sim)
        self._pose_update = kernels.pose_update if compiled else None
        #: the last pose-mode cycle's (TCP pose now, planned pose, their quaternions
        #: (2, 4), the distance between them) when the compiled cycle ran it, else None
        self.last: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None
        self._target: tuple[np.ndarray | None, np.ndarray] = (None, np.eye(4))
        #: the rotations' quaternions of the last cycles (this arm's and its messages')
        self.quats = QuatCache()
        self.q = np.asarray(sim.home_joints_deg, float).copy()
        start = self.tcp_pose()
        if path is None:
            path = straight_path(start, np.asarray(sim.path_direction),
                                 max(sim.path_length_mm, 1.0))
        self.path = ProgrammedPath(path)
        if mode == "pathcorr" and not np.allclose(self.path.at(0.0), start, atol=1e-3):
            q0 = self._ik(self.path.at(0.0), self.q)  # start where the program starts
            if q0 is None:
                raise EgmError("the programmed path's first pose is out of the robot's reach")
            self.q = q0
        self.s = 0.0                      # arc length run so far, mm
        self.corr_cmd = np.zeros(3)       # last received correction, mm (path frame)
        self.corr = np.zeros(3)           # correction applied (rate-limited), mm
        self.target: np.ndarray | None = None   # pose mode: latest received TCP target
        self.planned = self.tcp_pose()

    @property
    def running(self) -> bool:
        """Whether the program runs: always in pose mode, until the path's end in pathcorr."""
        return self.mode == "pose" or self.s < self.path.length

    def tcp_pose(self) -> np.ndarray:
        """TCP pose (4x4, mm) of the current joints."""
        return arm_forward(np, self._geometry, self.q[None], self.tool)[0][0]

    def rest_at(self, q_deg: np.ndarray) -> None:
        """Joints ``q_deg`` (6,) deg, at rest: the planned pose is the pose there and no target
        is pending."""
        q = np.asarray(q_deg, dtype=float).reshape(-1)
        if q.shape != (6,) or not np.isfinite(q).all():
            raise EgmError(f"rest_at needs 6 finite joint angles, got {q_deg!r}")
        self.q = q.copy()
        self.planned = self.tcp_pose()
        self.target = None

    def update(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Advance by ``dt`` s; returns (feedback joints, feedback TCP, planned TCP) at the start
        of the step, and the distance between the planned and the fed-back TCP, mm."""
        q_now = self.q.copy()
        if self._pose_update is not None:
            target = self.target
            if target is not None and target is not self._target[0]:
                # the kernel's copy of a new target (the controller's commands are read-only)
                self._target = (target, np.array(target, dtype=float, order="C"))
            planned = np.ascontiguousarray(self.planned, dtype=float)
            q, T_now, T_des, lag, quats = self._pose_update(
                self._g, self._R0, self.tool, self.q, planned,
                planned if target is None else self._target[1], target is not None,
                self.sim.tcp_speed_mm_s * dt, math.radians(self.sim.tcp_rot_speed_deg_s) * dt,
                self._speed, dt, _ROT_WEIGHT, _DAMPING)
            self.q, self.planned = q, T_des
            self.last = (T_now, T_des, quats, lag)
            return q_now, T_now, T_des, lag
        self.last = None
        if self.mode == "pathcorr":
            self.s = min(self.s + self.sim.path_speed_mm_s * dt, self.path.length)
            dc = self.corr_cmd - self.corr
            max_dc = self.sim.correction_speed_mm_s * dt
            n = float(np.linalg.norm(dc))
            self.corr = self.corr + (dc if n <= max_dc else dc * (max_dc / n))
            T_des = self.path.at(self.s)
            T_des[:3, 3] += T_des[:3, :3] @ self.corr
        elif self.target is not None:
            T_des = step_towards(self.planned, self.target, self.sim.tcp_speed_mm_s * dt,
                                 math.radians(self.sim.tcp_rot_speed_deg_s) * dt, self.quats)
        else:
            T_des = self.planned
        dq, T_now = self._newton_step(T_des)
        self.q = self.q + self._limit(dq, dt)
        self.planned = T_des
        lag = float(np.linalg.norm(T_des[:3, 3] - T_now[:3, 3]))
        return q_now, T_now, T_des, lag

    def _newton_step(self, T_des: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One damped Newton step towards ``T_des``: (joint step deg, TCP pose now).

        With the TCP Jacobian ``J`` per degree of :func:`arm_forward` (its angular rows times
        ``_ROT_WEIGHT``) and the error ``e`` (position; rotation vector of ``T_des R^T`` times
        ``_ROT_WEIGHT``): ``(J^T J + _DAMPING I) dq = J^T e``, compiled on one pose
        (``_kernels.newton_step``)."""
        return self._kernel(self._g, self._R0, self.tool, self.q,
                            np.ascontiguousarray(T_des, dtype=float), _ROT_WEIGHT, _DAMPING)

    def _limit(self, dq: np.ndarray, dt: float) -> np.ndarray:
        """Scale a joint step so that no axis exceeds its speed limit (path shape kept)."""
        over = float(np.max(np.abs(dq) / (self._speed * dt)))
        return dq / over if over > 1.0 else dq

    def _ik(self, T_tcp: np.ndarray, seed: np.ndarray) -> np.ndarray | None:
        """Controller joints for a TCP pose, or None when unreachable."""
        T_flange = T_tcp @ np.linalg.inv(self.tool)
        with torch.no_grad():
            q, ok = self.robot.ik(torch.as_tensor(T_flange[None], dtype=torch.float64),
                                  torch.as_tensor(seed[None], dtype=torch.float64))
        if not bool(ok[0]):
            return None
        return q[0].numpy().astype(float)


_POSE_KERNEL_AGREES: list[bool] = []


def _pose_kernel_agrees(robot: Any, sim: SimControllerConfig) -> bool:
    """Whether ``_kernels.pose_update`` computes what :meth:`ArmModel.update`'s numpy statement
    does, to the bit, on this machine: on a hundred cycles of an arm that follows moving
    targets (once per process, a few ms). Its dot products are the fused multiply-adds this
    machine's BLAS makes (``_kernels.blas_dot``) and its sines the C library's; a BLAS that
    sums otherwise (another CPU, another build) rounds differently, and there the arm keeps the
    numpy statement."""
    if not _POSE_KERNEL_AGREES:
        k = load_kernels(__package__)
        arm = ArmModel(robot, np.eye(4), sim, "pathcorr")   # (its joints and geometry)
        g, R0, tool, speed = arm._g, arm._R0, arm.tool, arm._speed
        rng = np.random.default_rng(3)
        home = arm.tcp_pose()
        ok = True
        dt, max_mm, max_rad = sim.period_s, sim.tcp_speed_mm_s * sim.period_s, math.radians(
            sim.tcp_rot_speed_deg_s) * sim.period_s
        planned, q = home, arm.q.copy()
        for i in range(120):
            if i % 20 == 0:   # a new target: a few mm and degrees away
                target = home.copy()
                target[:3, 3] += rng.normal(0.0, 5.0, 3)
                target[:3, :3] = quat_to_matrix(rng.normal(0.0, 0.05, 4) + [1.0, 0, 0, 0]) \
                    @ home[:3, :3]
            T_des = step_towards(planned, target, max_mm, max_rad) if i % 40 else planned
            dq, T_now = k.newton_step(g, R0, tool, q, T_des, _ROT_WEIGHT, _DAMPING)
            over = float(np.max(np.abs(dq) / (speed * dt)))
            q_ref = q + (dq / over if over > 1.0 else dq)
            lag = float(np.linalg.norm(T_des[:3, 3] - T_now[:3, 3]))
            got = k.pose_update(g, R0, tool, q, planned, target, bool(i % 40), max_mm, max_rad,
                                speed, dt, _ROT_WEIGHT, _DAMPING)
            ok &= (np.array_equal(got[0], q_ref) and np.array_equal(got[1], T_now)
                   and np.array_equal(got[2], T_des) and got[3] == lag
                   and np.array_equal(got[4][0], matrix_to_quat(T_now[:3, :3]))
                   and np.array_equal(got[4][1], matrix_to_quat(T_des[:3, :3])))
            planned, q = T_des, q_ref
        _POSE_KERNEL_AGREES.append(bool(ok))
    return _POSE_KERNEL_AGREES[0]
