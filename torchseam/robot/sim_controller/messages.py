"""The simulated IRC5's side of the EGM messages: ``EgmRobot`` out, the sensor's command in.

:class:`RobotMessages` builds each cycle's ``EgmRobot`` (feedback and planned joints and poses,
motor / MCI / RAPID state, utilisation) and stamps it as it leaves (sequence number, controller
time, wall clock); :func:`sensor_command` reads what a validated reply asks the robot to do.
Plain math on one pose: both run once per 4 ms cycle.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from torchseam.core.transforms import matrix_to_quat, quat_to_matrix
from torchseam.robot.egm.messages import (
    EgmHeader,
    EgmMCIState,
    EgmMotorState,
    EgmRapidCtrlExecState,
    EgmRobot,
)

_U32 = 0xFFFFFFFF
_CONVERGED_MM = 0.05   # |planned - feedback| below this: mciConvergenceMet


class RobotMessages:
    """``EgmRobot`` for each cycle, numbered from 1.

    Args:
        period_s: the control cycle, s (utilisation is compute time over it).
        quat: the (3, 3) rotation -> quaternion conversion of the poses (default
            :func:`~torchseam.core.transforms.matrix_to_quat`; the simulated controller gives
            its arm's :class:`~torchseam.robot.sim_controller.arm.QuatCache`).
    """

    def __init__(self, period_s: float, quat=matrix_to_quat) -> None:
        self.period = period_s
        self._quat = quat   # rotation -> quaternion (the arm's QuatCache: the same numbers)
        self._seqno = 0
        self._t0 = time.perf_counter()
        #: the next :meth:`build`'s feedback and planned poses with their quaternions (2, 4)
        #: and the distance between their positions, when its caller has them (the arm's
        #: compiled cycle), else None
        self.known: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None

    def build(self, q: np.ndarray, T: np.ndarray, q_plan: np.ndarray, T_plan: np.ndarray,
              running: bool, compute_s: float) -> Any:
        """The next ``EgmRobot``: feedback joints ``q`` (deg) and TCP ``T`` (4x4 mm), planned
        joints and TCP, whether RAPID runs, the cycle's compute time (s). Header and clocks are
        stamped by :meth:`stamp` when it is sent. Where :attr:`known` holds these very poses
        (the same objects), their quaternions and distance are taken from it (the same
        numbers as computed here); it is cleared."""
        msg = EgmRobot()
        known, self.known = self.known, None
        quats: Any
        if known is not None and known[0] is T and known[1] is T_plan:
            quats, dist = known[2], known[3]
        else:
            quats = (self._quat(T[:3, :3]), self._quat(T_plan[:3, :3]))
            dist = float(np.linalg.norm(T[:3, 3] - T_plan[:3, 3]))
        for part, joints, pose, quat in ((msg.feedBack, q, T, quats[0]),
                                         (msg.planned, q_plan, T_plan, quats[1])):
            part.joints.joints.extend(np.asarray(joints, dtype=float).tolist())
            _fill(part.cartesian, pose, quat)
        msg.motorState.state = EgmMotorState.MOTORS_ON
        msg.mciState.state = EgmMCIState.MCI_RUNNING
        msg.mciConvergenceMet = dist < _CONVERGED_MM
        msg.rapidExecState.state = (EgmRapidCtrlExecState.RAPID_RUNNING if running
                                    else EgmRapidCtrlExecState.RAPID_STOPPED)
        msg.utilizationRate = 100.0 * compute_s / self.period
        return msg

    def stamp(self, msg: Any) -> bytes:
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


def fill_pose(pose: Any, T: np.ndarray, quat=matrix_to_quat) -> None:
    """Position (mm), quaternion (w, x, y, z) and ABB EulerZYX angles (deg) of a 4x4 pose
    (``quat``: the rotation -> quaternion conversion)."""
    _fill(pose, T, quat(T[:3, :3]))


def _fill(pose: Any, T: np.ndarray, quat: np.ndarray) -> None:
    """:func:`fill_pose` with the rotation's quaternion ``quat`` (4,) given."""
    m = np.asarray(T, dtype=float).tolist()
    pos, o, e = pose.pos, pose.orient, pose.euler
    pos.x, pos.y, pos.z = m[0][3], m[1][3], m[2][3]
    o.u0, o.u1, o.u2, o.u3 = np.asarray(quat, dtype=float).tolist()
    # R = Rz(z) Ry(y) Rx(x) (ABB EulerZYX); plain math: scipy objects cost more per cycle
    e.y = math.degrees(math.asin(max(-1.0, min(1.0, -m[2][0]))))
    e.z = math.degrees(math.atan2(m[1][0], m[0][0]))
    e.x = math.degrees(math.atan2(m[2][1], m[2][2]))


def sensor_command(msg: Any, mode: str) -> np.ndarray | None:
    """What a validated reply commands: in ``pose`` mode the target TCP pose (4x4, mm; Euler
    angles win over the quaternion, as on an IRC5), None for a zero quaternion; in ``pathcorr``
    the correction (3,) mm in the path frame."""
    if mode != "pose":
        p = msg.pathCorr.pos
        return np.array([p.x, p.y, p.z])
    c = msg.planned.cartesian
    if c.HasField("euler"):
        e = c.euler
        R = Rotation.from_euler("ZYX", [e.z, e.y, e.x], degrees=True).as_matrix()
    else:
        o = c.orient
        q = np.array([o.u0, o.u1, o.u2, o.u3])
        n = float(np.linalg.norm(q))
        if not n > 0.0:
            return None
        R = quat_to_matrix(q / n)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [c.pos.x, c.pos.y, c.pos.z]
    return T
