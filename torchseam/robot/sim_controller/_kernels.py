"""The simulated controller's compiled kernel (numba): one damped Newton step of the arm.

The simulated IRC5 moves its joints every 4 ms cycle by one damped least-squares step towards
the pose it plans; in the demo and the virtual cell that runs ten times a camera frame. As
numpy calls (the batched closed-form forward kinematics of
:func:`~torchseam.robot.kinematics.arm_forward` on one pose, a rotation vector, a 6 x 6 solve)
the interpreter overhead is almost all of its time. This kernel is the same arithmetic on one
pose in scalars; ``tests/test_sim_controller.py`` holds it to the numpy statement (1e-9).
The signature is given, so it is compiled (or loaded from numba's on-disk cache) when this
module is imported, which :class:`~torchseam.robot.sim_controller.arm.ArmModel` does when it
is built.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit("Tuple((f8[::1], f8[:, ::1]))(f8[::1], f8[:, ::1], f8[:, ::1], f8[::1], "
            "f8[:, ::1], f8, f8)", cache=True, nogil=True)
def newton_step(g, R0, tool, q_deg, T_des, rot_weight, damping):  # pragma: no cover - compiled
    """One damped Newton step of the controller joints ``q_deg`` (6,) towards the TCP pose
    ``T_des`` (4, 4): ``(joint step (6,) deg, the TCP pose now (4, 4))``.

    ``g``: (a1, d1, a2, a3, d4, d6) mm of the arm's closed form; ``R0`` tool0's rotation in
    link 6; ``tool`` the TCP in the flange frame. The step solves
    ``(J^T J + damping I) dq = J^T e`` with the TCP Jacobian ``J`` per degree, its angular rows
    and the orientation error ``e[3:]`` (the rotation vector of ``T_des R^T``) weighted by
    ``rot_weight`` mm/rad (as :meth:`ArmModel._newton_step` states it in numpy).
    """
    a1, d1, a2, a3, d4, d6 = g[0], g[1], g[2], g[3], g[4], g[5]
    q = q_deg * (math.pi / 180.0)
    c1, s1 = math.cos(q[0]), math.sin(q[0])
    c2, s2 = math.cos(q[1]), math.sin(q[1])
    cb, sb = math.cos(q[2]), math.sin(q[2])
    c4, s4 = math.cos(q[3]), math.sin(q[3])
    c5, s5 = math.cos(q[4]), math.sin(q[4])
    c6, s6 = math.cos(q[5]), math.sin(q[5])
    z1 = np.array([0.0, 0.0, 1.0])
    y1 = np.array([-s1, c1, 0.0])
    x3 = np.array([c1 * cb, s1 * cb, -sb])
    z3 = np.array([c1 * sb, s1 * sb, cb])
    p2 = np.array([a1 * c1, a1 * s1, d1])
    p3 = p2 + a2 * np.array([c1 * s2, s1 * s2, c2])
    pw = p3 + d4 * x3 + a3 * z3
    y4 = c4 * y1 + s4 * z3
    z4 = c4 * z3 - s4 * y1
    x5 = c5 * x3 - s5 * z4
    z5 = s5 * x3 + c5 * z4
    y6 = c6 * y4 + s6 * z5
    z6 = c6 * z5 - s6 * y4
    pe = pw + d6 * x5
    F = np.empty((3, 3))
    F[:, 0], F[:, 1], F[:, 2] = x5, y6, z6
    R6 = F @ R0
    pt = pe + R6 @ np.ascontiguousarray(tool[:3, 3])
    R = R6 @ np.ascontiguousarray(tool[:3, :3])
    axes = (z1, y1, y1, x3, y4, x5)
    arms = (pt, p3 - p2, pt - p3, pt - pw, pt - pw, pt - pe)
    J = np.zeros((6, 6))
    per_deg = math.pi / 180.0
    for i in range(6):
        a, r = axes[i], arms[i]
        J[0, i] = (a[1] * r[2] - a[2] * r[1]) * per_deg
        J[1, i] = (a[2] * r[0] - a[0] * r[2]) * per_deg
        J[2, i] = (a[0] * r[1] - a[1] * r[0]) * per_deg
        if i != 1:  # axis 2 moves the forearm parallel to itself: no rotation
            J[3, i] = a[0] * per_deg * rot_weight
            J[4, i] = a[1] * per_deg * rot_weight
            J[5, i] = a[2] * per_deg * rot_weight
    # the orientation error: the rotation vector of T_des R^T (angles below pi)
    E = np.ascontiguousarray(T_des[:3, :3]) @ np.ascontiguousarray(R.T)
    c = min(1.0, max(-1.0, (E[0, 0] + E[1, 1] + E[2, 2] - 1.0) / 2.0))
    ang = math.acos(c)
    sn = math.sin(ang)
    k = ang / (2.0 * sn) if sn > 1e-12 else 0.5
    err = np.empty(6)
    err[0] = T_des[0, 3] - pt[0]
    err[1] = T_des[1, 3] - pt[1]
    err[2] = T_des[2, 3] - pt[2]
    err[3] = (E[2, 1] - E[1, 2]) * k * rot_weight
    err[4] = (E[0, 2] - E[2, 0]) * k * rot_weight
    err[5] = (E[1, 0] - E[0, 1]) * k * rot_weight
    A = J.T @ J
    for i in range(6):
        A[i, i] += damping
    dq = np.linalg.solve(A, J.T @ err)
    T = np.zeros((4, 4))
    T[:3, :3] = R
    T[:3, 3] = pt
    T[3, 3] = 1.0
    return dq, T
