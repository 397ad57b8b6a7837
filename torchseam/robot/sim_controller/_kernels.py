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
from llvmlite import ir
from numba.core import types
from numba.core.extending import intrinsic


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


@intrinsic
def _fma(typingctx, a, b, c):  # pragma: no cover - compiled
    """``a * b + c`` in float64 rounded once (LLVM's ``llvm.fma.f64``)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        f = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [f], ir.FunctionType(f, [f, f, f]))
        return builder.call(fn, args)

    return sig, codegen


@numba.njit("f8(f8[::1], f8[::1])", cache=True, nogil=True)
def blas_dot(a, b):  # pragma: no cover - compiled
    """``np.dot`` of two short float64 vectors as this machine's BLAS (``ddot``) computes it:
    a fused multiply-add per element, in order, from 0 (``ArmModel`` checks that it agrees
    before using :func:`pose_update`)."""
    s = 0.0
    for i in range(len(a)):
        s = _fma(a[i], b[i], s)  # type: ignore[call-arg]
    return s


@numba.njit(cache=True, nogil=True)
def _quat(R):  # pragma: no cover - compiled
    """``torchseam.core.transforms.matrix_to_quat`` of one (3, 3) rotation, its arithmetic in
    its order (Shepperd's method, normalised, w >= 0)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    k, best = 0, tr
    if R[0, 0] > best:
        k, best = 1, R[0, 0]
    if R[1, 1] > best:
        k, best = 2, R[1, 1]
    if R[2, 2] > best:
        k = 3
    q = np.empty(4)
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q[0], q[1] = 0.25 * s, (R[2, 1] - R[1, 2]) / s
        q[2], q[3] = (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q[0], q[1] = (R[2, 1] - R[1, 2]) / s, 0.25 * s
        q[2], q[3] = (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 - R[0, 0] + R[1, 1] - R[2, 2], 0.0))
        q[0], q[1] = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s
        q[2], q[3] = 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 - R[0, 0] - R[1, 1] + R[2, 2], 0.0))
        q[0], q[1] = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s
        q[2], q[3] = (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q /= math.sqrt(blas_dot(q, q))
    if q[0] < 0:
        q = -q
    return q


@numba.njit(cache=True, nogil=True)
def _slerp_matrix(q0, q1, u):  # pragma: no cover - compiled
    """``quat_to_matrix(slerp(q0, q1, u))`` of ``torchseam.core.transforms``, their arithmetic
    in their order."""
    d = blas_dot(q0, q1)
    if d < 0.0:
        q1, d = -q1, -d
    d = min(1.0, d)
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
    else:
        a = math.acos(d)
        q = (math.sin((1.0 - u) * a) * q0 + math.sin(u * a) * q1) / math.sin(a)
    q = q / math.sqrt(blas_dot(q, q))
    q = q / math.sqrt(blas_dot(q, q))   # quat_to_matrix normalises once more
    w, x, y, z = q[0], q[1], q[2], q[3]
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return R


@numba.njit("Tuple((f8[::1], f8[:, ::1], f8[:, ::1], f8, f8[:, ::1]))(f8[::1], f8[:, ::1], "
            "f8[:, ::1], f8[::1], f8[:, ::1], f8[:, ::1], b1, f8, f8, f8[::1], f8, f8, f8)",
            cache=True, nogil=True)
def pose_update(g, R0, tool, q_deg, planned, target, has_target, max_mm, max_rad, speed, dt,
                rot_weight, damping):  # pragma: no cover - compiled
    """One pose-mode cycle of ``ArmModel.update`` (its numpy statement's arithmetic, in its
    order): the planned pose moved towards ``target`` (when ``has_target``) by at most
    ``max_mm`` and ``max_rad`` (``arm.step_towards``), one :func:`newton_step` towards it, the
    step scaled to the joint speeds ``speed`` (deg/s) over ``dt``. Returns the new joints, the
    TCP pose at the old ones, the planned pose, the distance between the two poses' positions
    and the quaternions (w, x, y, z) of their rotations, (2, 4)."""
    if has_target:
        T_des = np.eye(4)
        d = target[:3, 3] - planned[:3, 3]
        n = math.sqrt(blas_dot(d, d))
        if n <= max_mm:
            T_des[:3, 3] = target[:3, 3]
        else:
            T_des[:3, 3] = planned[:3, 3] + d * (max_mm / n)
        q0, q1 = _quat(planned[:3, :3]), _quat(target[:3, :3])
        ang = 2.0 * math.acos(min(1.0, abs(blas_dot(q0, q1))))
        u = 1.0 if ang <= max_rad else max_rad / ang
        T_des[:3, :3] = _slerp_matrix(q0, q1, u)
    else:
        T_des = planned
    dq, T_now = newton_step(g, R0, tool, q_deg, T_des, rot_weight, damping)
    over = np.max(np.abs(dq) / (speed * dt))
    q_new = q_deg + (dq / over if over > 1.0 else dq)
    e = T_des[:3, 3] - T_now[:3, 3]
    lag = math.sqrt(blas_dot(e, e))
    quats = np.empty((2, 4))
    quats[0] = _quat(T_now[:3, :3])
    quats[1] = _quat(T_des[:3, :3])
    return q_new, T_now, T_des, lag, quats
