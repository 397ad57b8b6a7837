"""Rigid transforms and quaternions (ABB order w, x, y, z), numpy side: the one home of the
rotation helpers (the angle between two quaternions, a rotation about a coordinate axis or any
axis, the cross product of 3-vectors).

The batched torch versions live in :mod:`pytorch_kinematics.transforms` (same w-first order).
"""

from __future__ import annotations

import math

import numpy as np


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices (one unit quaternion
    in closed form: the simulated controller converts one per 4 ms cycle)."""
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):
        w, x, y, z = q / np.linalg.norm(q)
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    from scipy.spatial.transform import Rotation  # (batches only: --help stays light)

    return Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(
        *q.shape[:-1], 3, 3)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 4) quaternions (w, x, y, z) with w >= 0."""
    R = np.asarray(R, dtype=float)
    if R.shape == (3, 3):
        return _matrix_to_quat_one(R)
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(scalar_first=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(*R.shape[:-2], 4)


def _matrix_to_quat_one(R: np.ndarray) -> np.ndarray:
    """One rotation (Shepperd's method, the largest of 4 w^2, 4 x^2, 4 y^2, 4 z^2 as pivot):
    the live loop converts one pose per step, where scipy's per-call overhead would be most
    of the cost. Same answers as the scipy path (tests/test_config.py)."""
    m = R.tolist()
    tr = m[0][0] + m[1][1] + m[2][2]
    k = max(range(4), key=lambda i: (tr, m[0][0], m[1][1], m[2][2])[i])
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = (0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s)
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + m[0][0] - m[1][1] - m[2][2], 0.0))
        q = ((m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s)
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 - m[0][0] + m[1][1] - m[2][2], 0.0))
        q = ((m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 - m[0][0] - m[1][1] + m[2][2], 0.0))
        q = ((m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s)
    out = np.array(q)
    out /= np.linalg.norm(out)
    return -out if out[0] < 0 else out


def rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) (axis times angle, rad) of rotations (..., 3, 3) with angles
    below pi, in plain numpy (scipy's Rotation objects cost more than the arithmetic in the
    4 ms loops that call this).

    Example:
        >>> rotvec(rotation_about(np.array([0.0, 0.0, 1.0]), 0.5)).round(6).tolist()
        [0.0, 0.0, 0.5]
    """
    c = np.clip((np.einsum("...ii", R) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.arccos(c)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.sin(ang)
    k = np.where(sin > 1e-12, ang / (2.0 * np.where(sin > 1e-12, sin, 1.0)), 0.5)
    return v * k[..., None]


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Unit quaternion (4,) ``u`` of the way from ``q0`` to ``q1`` (w, x, y, z), the short way.

    Nearly equal quaternions are interpolated linearly and renormalised: there that follows
    the arc as closely as needed and avoids dividing by the sine of a vanishing angle. Plain
    math on one pair: the simulated controller interpolates once per 4 ms cycle.

    Example:
        >>> q = slerp(np.array([1.0, 0, 0, 0]), np.array([0.0, 0, 0, 1]), 0.5)
        >>> np.round(q, 6).tolist()
        [0.707107, 0.0, 0.0, 0.707107]
    """
    q0, q1 = np.asarray(q0, dtype=float), np.asarray(q1, dtype=float)
    d = float(np.dot(q0, q1))
    if d < 0.0:  # q and -q are the same rotation: take the nearer one
        q1, d = -q1, -d
    d = min(1.0, d)
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
    else:
        a = math.acos(d)
        q = (math.sin((1.0 - u) * a) * q0 + math.sin(u * a) * q1) / math.sin(a)
    return q / np.linalg.norm(q)


def pose_matrix(position: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """(..., 3) position + (..., 4) quaternion -> (..., 4, 4) homogeneous transform."""
    position = np.asarray(position, dtype=float)
    T = np.zeros((*position.shape[:-1], 4, 4))
    T[..., :3, :3] = quat_to_matrix(quaternion)
    T[..., :3, 3] = position
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms."""
    R = T[..., :3, :3]
    out = np.zeros_like(T)
    out[..., :3, :3] = np.swapaxes(R, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", R, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply (4, 4) transform(s) to (..., 3) points."""
    return np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]


def quat_angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    """Rotation angle between two unit quaternions (4,) (w, x, y, z), degrees (q and -q are the
    same rotation)."""
    return 2.0 * math.degrees(math.acos(min(1.0, abs(float(np.dot(q1, q2))))))


def axis_rotation(axis: int, deg: float) -> np.ndarray:
    """(3, 3) rotation by ``deg`` about coordinate axis ``axis`` (0 x, 1 y, 2 z)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    M = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    M[i, i], M[i, j], M[j, i], M[j, j] = c, -s, s, c
    return M


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (3,) in plain floats: ``np.cross`` costs ~25 us a call on
    3-vectors, this ~2 us (the live loop plans a pose per step with a few of them)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def cross(a, b):  # noqa: ANN001, ANN201 - numpy or torch arrays alike
    """Cross product over the last axis of (..., 3) arrays, numpy or torch alike (indexing
    only: ``np.cross`` is slow on small batches)."""
    return a[..., [1, 2, 0]] * b[..., [2, 0, 1]] - a[..., [2, 0, 1]] * b[..., [1, 2, 0]]


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """3x3 rotation about a unit ``axis`` by ``angle_rad``."""
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle_rad).as_matrix()
