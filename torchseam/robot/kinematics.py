"""Kinematic model of the ABB IRB 1410: FK, Jacobian and IK, batched in torch.

Joint values at this module's boundary are **controller values in degrees** (what the FlexPendant,
RAPID ``jointtarget`` and EGM show). The URDF (``urdf/irb1410.urdf``) and pytorch-kinematics use
URDF values in radians, where ``joint_3 = axis3 - axis2`` (axis 3 is driven through a
parallelogram); :func:`controller_to_urdf` / :func:`urdf_to_controller` are the only places that
convert. Poses are 4x4 transforms of ``tool0`` (the flange) in the robot base, in **mm**;
quaternions are ABB order (w, x, y, z).

Forward kinematics and the Jacobian come from the pytorch-kinematics chain built from the URDF.
IK is analytic by default: the IRB 1410 has a spherical wrist and no lateral offsets, so every
pose has up to 8 closed-form solutions (front/back x elbow up/down x wrist flip); the one nearest
a seed is returned, and every answer is checked against the chain's FK. The arm lengths the
closed form needs are read from the chain itself, so the URDF stays the single source.
``method="numeric"`` runs pytorch-kinematics' ``PseudoInverseIK`` instead (seeded, or with random
restarts) -- slower and kept for comparison (``bench/ik.py``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytorch_kinematics as pk
import torch
from pytorch_kinematics.transforms import rotation_conversions as rc

from torchseam import shipped
from torchseam.core.errors import TorchseamError
from torchseam.core.transforms import cross
from torchseam.robot.config import RobotConfig, load_robot_config

#: The shipped URDF (written from the IRB 1410's standard DH table: the ARTE toolbox,
#: robots/ABB/IRB1410/parameters.m, the same numbers in Malla & Shanmugavel, Industrial Robot
#: 51(5) 2024; the repository's ``urdf/irb1410.urdf``, shipped in the package).
URDF_PATH = shipped("urdf") / "irb1410.urdf"
JOINT_NAMES = tuple(f"joint_{i}" for i in range(1, 7))
EEF_LINK = "tool0"

Tensor = torch.Tensor
Array = Any  # a numpy array or a torch tensor (the closed-form helpers take either)


class RobotInputError(TorchseamError, ValueError):
    """Joint values or poses handed to the robot model have a bad shape, NaN or bad rotation."""


class URDFError(TorchseamError):
    """The URDF cannot be read, or is not an IRB 1410-like 6R arm with a spherical wrist."""


# --------------------------------------------------------------------------- joint conventions

def controller_to_urdf(q_deg: Tensor) -> Tensor:
    """Controller joint values (deg) -> URDF joint values (rad).

    The controller's axis 3 is the forearm angle measured from the horizontal (parallelogram), the
    URDF's ``joint_3`` is measured from link 2: ``joint_3 = axis3 - axis2``.

    Args:
        q_deg: (..., 6) controller values, degrees.

    Returns:
        (..., 6) URDF values, radians.

    Example:
        >>> controller_to_urdf(torch.tensor([0.0, 30.0, 10.0, 0.0, 0.0, 0.0]))[2].rad2deg()
        tensor(-20.)
    """
    q = torch.as_tensor(q_deg)
    j3 = q[..., 2:3] - q[..., 1:2]
    return torch.deg2rad(torch.cat([q[..., :2], j3, q[..., 3:]], dim=-1))


def urdf_to_controller(q_rad: Tensor) -> Tensor:
    """URDF joint values (rad) -> controller joint values (deg); inverse of
    :func:`controller_to_urdf` (``axis3 = joint_3 + joint_2``).

    Args:
        q_rad: (..., 6) URDF values, radians.

    Returns:
        (..., 6) controller values, degrees.
    """
    q = torch.rad2deg(torch.as_tensor(q_rad))
    a3 = q[..., 2:3] + q[..., 1:2]
    return torch.cat([q[..., :2], a3, q[..., 3:]], dim=-1)


def _coupling_matrix(dtype: torch.dtype, device: torch.device | str) -> Tensor:
    """d(URDF q)/d(controller q), both in rad: joint_3 = axis3 - axis2."""
    C = torch.eye(6, dtype=dtype, device=device)
    C[2, 1] = -1.0
    return C


# --------------------------------------------------------------------------- pose helpers

def pose_to_xyzq(T: Tensor) -> Tensor:
    """(..., 4, 4) poses -> (..., 7) ``x y z`` (pose units) + quaternion ``w x y z`` with w >= 0.

    Example:
        >>> pose_to_xyzq(torch.eye(4, dtype=torch.float64))
        tensor([0., 0., 0., 1., 0., 0., 0.], dtype=torch.float64)
    """
    T = torch.as_tensor(T)
    q = rc.matrix_to_quaternion(T[..., :3, :3])
    q = torch.where(q[..., :1] < 0, -q, q)  # one sign convention: w >= 0
    return torch.cat([T[..., :3, 3], q], dim=-1)


def xyzq_to_pose(xyzq: Tensor) -> Tensor:
    """(..., 7) ``x y z w qx qy qz`` -> (..., 4, 4) poses; the quaternion must be unit (1e-3).

    Raises:
        RobotInputError: NaN, or a quaternion that is not unit length.
    """
    x = torch.as_tensor(xyzq)
    if x.shape[-1:] != (7,):
        raise RobotInputError(f"xyzq: expected shape (..., 7), got {tuple(x.shape)}")
    if not torch.isfinite(x).all():
        raise RobotInputError(f"xyzq: pose {_first_bad(~torch.isfinite(x).all(-1))} is not finite")
    norm = x[..., 3:].norm(dim=-1)
    bad = (norm - 1.0).abs() > 1e-3
    if bad.any():
        i = _first_bad(bad)
        raise RobotInputError(f"xyzq: pose {i}: quaternion norm {norm.reshape(-1)[i]:.6f} is "
                              "not 1 (w, x, y, z expected)")
    T = torch.zeros(*x.shape[:-1], 4, 4, dtype=x.dtype, device=x.device)
    T[..., :3, :3] = rc.quaternion_to_matrix(x[..., 3:] / norm[..., None])
    T[..., :3, 3] = x[..., :3]
    T[..., 3, 3] = 1.0
    return T


def rotation_angle(Ra: Array, Rb: Array) -> Array:
    """(...) angle in rad between rotations (..., 3, 3), numpy or torch; accurate near 0."""
    xp = torch if isinstance(Ra, torch.Tensor) else np
    D = xp.swapaxes(Ra, -1, -2) @ Rb
    s = xp.linalg.norm(xp.stack([D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0],
                                 D[..., 1, 0] - D[..., 0, 1]], axis=-1), axis=-1) / 2
    c = (D[..., 0, 0] + D[..., 1, 1] + D[..., 2, 2] - 1) / 2
    return xp.atan2(s, c)


def validate_poses(T: Tensor | np.ndarray, name: str = "T_target") -> None:
    """Raise :class:`RobotInputError` unless ``T`` is (..., 4, 4) finite rigid transforms."""
    xp = torch if isinstance(T, torch.Tensor) else np
    if T.ndim < 2 or tuple(T.shape[-2:]) != (4, 4):
        raise RobotInputError(f"{name}: expected shape (..., 4, 4), got {tuple(T.shape)}")
    flat = T.reshape(-1, 4, 4)
    bad = ~xp.isfinite(flat).all(axis=-1).all(axis=-1)
    if bad.any():
        raise RobotInputError(f"{name}: pose {_first_bad(bad)} is not finite")
    bottom = flat[:, 3] - _const(xp, [0.0, 0.0, 0.0, 1.0], flat)
    bad = xp.amax(xp.abs(bottom), axis=-1) > 1e-9
    if bad.any():
        raise RobotInputError(f"{name}: pose {_first_bad(bad)}: last row must be 0 0 0 1")
    R = flat[:, :3, :3]
    dev = xp.amax(xp.abs(xp.swapaxes(R, -1, -2) @ R - _const(xp, np.eye(3), R)), axis=(-2, -1))
    bad = (dev > 1e-6) | (xp.linalg.det(R) < 0)
    if bad.any():
        i = _first_bad(bad)
        raise RobotInputError(f"{name}: pose {i}: rotation is not orthonormal "
                              f"(|R^T R - I| = {float(dev[i]):.2e}) or is a reflection")


def _first_bad(mask: Tensor | np.ndarray) -> int:
    return int(np.flatnonzero(to_numpy(mask).reshape(-1))[0])


def _wrap(a: Tensor) -> Tensor:
    """Angles (rad) wrapped to [-pi, pi)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


# --------------------------------------------------------------------------- results

@dataclass(frozen=True)
class IKSolution:
    """Result of :meth:`IRB1410.solve_ik`, all tensors batched over N goals.

    Attributes:
        q_deg: (N, 6) controller joints; the best attempt where ``reached`` is False.
        reached: (N,) a solution reaches the goal within the configured tolerances.
        in_range: (N,) the returned joints respect the axis ranges (coupled axis-3 check incl.).
        pos_err_mm: (N,) FK position residual of ``q_deg`` (pytorch-kinematics FK).
        rot_err_deg: (N,) FK orientation residual of ``q_deg``.
    """

    q_deg: Tensor
    reached: Tensor
    in_range: Tensor
    pos_err_mm: Tensor
    rot_err_deg: Tensor

    @property
    def ok(self) -> Tensor:
        """(N,) reached and within the axis ranges."""
        return self.reached & self.in_range


@dataclass(frozen=True)
class _ArmGeometry:
    """Lengths (mm) and the tool0 rotation at zero, read from the chain, for the closed form."""

    a1: float
    d1: float
    a2: float
    a3: float
    d4: float
    d6: float
    R0: np.ndarray  # tool0 orientation in link_6 (= in base at zero)

    @property
    def L3(self) -> float:  # joint 3 -> wrist centre
        return math.hypot(self.a3, self.d4)

    @property
    def phi(self) -> float:  # angle of the wrist centre off link 2's direction at joint_3 = 0
        return math.atan2(self.d4, self.a3)


# --------------------------------------------------------------------------- the robot

class IRB1410:
    """ABB IRB 1410 kinematics, batched in torch (default float64 on the CPU).

    Args:
        config: limits and IK tolerances (``configs/robot.yaml``: :func:`load_irb1410` reads it
            and builds the model).
        urdf_path: URDF to build the chain from (default ``urdf/irb1410.urdf``).
        dtype: float dtype of every tensor the model returns.
        device: torch device of the chain and the results.

    Raises:
        URDFError: unreadable URDF, wrong joint names, or not the 6R spherical-wrist structure.

    Example:
        >>> from torchseam.robot.config import load_robot_config
        >>> robot = IRB1410(load_robot_config())
        >>> T = robot.fk(torch.zeros(1, 6, dtype=torch.float64))
        >>> T[0, :3, 3]
        tensor([ 955.0000,    0.0000, 1195.0000], dtype=torch.float64)
        >>> q, ok = robot.ik(T)
        >>> bool(ok[0])
        True
    """

    def __init__(self, config: RobotConfig, urdf_path: str | os.PathLike[str] | None = None,
                 dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> None:
        self.config = config
        self.urdf_path = Path(urdf_path) if urdf_path is not None else URDF_PATH
        self.dtype = dtype
        self.device = torch.device(device)
        try:
            data = self.urdf_path.read_bytes()
        except OSError as e:
            raise URDFError(f"{self.urdf_path}: cannot read URDF ({e.strerror or e})") from None
        try:
            chain = pk.build_serial_chain_from_urdf(data, EEF_LINK)
        except Exception as e:  # lxml / parser errors: the message is all the user needs
            raise URDFError(f"{self.urdf_path}: cannot build a chain to {EEF_LINK!r} ({e})"
                            ) from None
        # pk parses URDF origins in float32 before .to(): offsets carry ~4e-8 m of rounding.
        self.chain = chain.to(dtype=dtype, device=self.device)
        names = tuple(self.chain.get_joint_parameter_names())
        if names != JOINT_NAMES:
            raise URDFError(f"{self.urdf_path}: expected joints {', '.join(JOINT_NAMES)}, got "
                            f"{', '.join(names)}")
        self._eef = int(self.chain.get_frame_indices(EEF_LINK)[0])
        self._C = _coupling_matrix(dtype, self.device)
        self._mm = torch.ones(4, 4, dtype=dtype, device=self.device)
        self._mm[:3, 3] = 1000.0  # scales the translation column m -> mm
        self.geometry = self._read_geometry()
        ax = self.config.axes
        self.min_deg = torch.tensor(ax.min_deg, dtype=dtype, device=self.device)
        self.max_deg = torch.tensor(ax.max_deg, dtype=dtype, device=self.device)
        self.home_deg = torch.tensor(self.config.home_deg, dtype=dtype, device=self.device)

    #: ``(..., 4, 4)`` -> ``(..., 7)`` x y z + quaternion w x y z (see :func:`pose_to_xyzq`).
    pose_to_xyzq = staticmethod(pose_to_xyzq)
    #: ``(..., 7)`` -> ``(..., 4, 4)`` (see :func:`xyzq_to_pose`).
    xyzq_to_pose = staticmethod(xyzq_to_pose)

    # ------------------------------------------------------------------ input checks
    def _joints(self, q_deg: Tensor | np.ndarray, name: str = "q_deg") -> Tensor:
        q = torch.as_tensor(q_deg, dtype=self.dtype, device=self.device)
        if q.ndim == 0 or q.shape[-1] != 6:
            raise RobotInputError(f"{name}: expected shape (..., 6) controller degrees, got "
                                  f"{tuple(q.shape)}")
        if not torch.isfinite(q).all():
            bad = ~torch.isfinite(q).all(-1)
            raise RobotInputError(f"{name}: row {_first_bad(bad)} is not finite")
        return q

    def _poses(self, T: Tensor | np.ndarray, name: str = "T_target") -> Tensor:
        T = torch.as_tensor(T, dtype=self.dtype, device=self.device)
        validate_poses(T, name)
        return T

    def _seed(self, q_seed_deg: Tensor | np.ndarray | None, n: int) -> Tensor:
        if q_seed_deg is None:
            return self.home_deg.expand(n, 6)
        q = self._joints(q_seed_deg, "q_seed_deg").reshape(-1, 6)
        if q.shape[0] == 1:
            return q.expand(n, 6)
        if q.shape[0] != n:
            raise RobotInputError(f"q_seed_deg: expected 1 or {n} seeds, got {q.shape[0]}")
        return q

    # ------------------------------------------------------------------ FK and Jacobian
    def fk(self, q_deg: Tensor | np.ndarray) -> Tensor:
        """Pose of tool0 in the base frame (pytorch-kinematics FK).

        Args:
            q_deg: (..., 6) controller joint values, degrees.

        Returns:
            (..., 4, 4) homogeneous transforms, translation in mm. Differentiable.

        Raises:
            RobotInputError: wrong shape or non-finite values.
        """
        q = self._joints(q_deg)
        th = controller_to_urdf(q.reshape(-1, 6))
        T = self.chain.forward_kinematics_tensor(th)[self._eef] * self._mm
        return T.reshape(*q.shape[:-1], 4, 4)

    def jacobian(self, q_deg: Tensor | np.ndarray) -> Tensor:
        """Geometric Jacobian of tool0 in the base frame w.r.t. the controller axes.

        Rows 0-2: linear velocity of the flange origin in mm per rad; rows 3-5: angular velocity
        in rad per rad. Columns: controller axes 1..6 (so column 2 is the parallelogram motion:
        axis 2 turns with axis 3 held).

        Args:
            q_deg: (..., 6) controller joint values, degrees.

        Returns:
            (..., 6, 6) Jacobian.
        """
        q = self._joints(q_deg)
        th = controller_to_urdf(q.reshape(-1, 6))
        J = self.chain.jacobian_tensor(th) @ self._C
        J = torch.cat([J[:, :3] * 1000.0, J[:, 3:]], dim=1)
        return J.reshape(*q.shape[:-1], 6, 6)

    # ------------------------------------------------------------------ limits
    def range_excess(self, q_deg: Tensor) -> Tensor:
        """How far each axis lies outside its range (deg): 0 inside, > 0 above max, < 0 below min.

        Axis 3 is checked on the controller value or on ``axis3 - axis2`` according to
        ``axis3_range_applies_to`` in the config.

        Args:
            q_deg: (..., 6) controller joint values.

        Returns:
            (..., 6) signed excess, degrees.
        """
        q = torch.as_tensor(q_deg, dtype=self.dtype, device=self.device)
        return range_excess(q, self.min_deg, self.max_deg, self.axis3_difference)

    @property
    def axis3_difference(self) -> bool:
        """True where axis 3's range applies to ``axis3 - axis2`` (config)."""
        return self.config.axis3_range_applies_to == "difference"

    def in_range(self, q_deg: Tensor) -> Tensor:
        """(..., ) True where every axis is within its range (tolerance 1e-9 deg)."""
        return (self.range_excess(q_deg).abs() <= 1e-9).all(dim=-1)

    # ------------------------------------------------------------------ IK
    def ik(self, T_target: Tensor | np.ndarray, q_seed_deg: Tensor | np.ndarray | None = None
           ) -> tuple[Tensor, Tensor]:
        """Joints reaching tool0 poses, nearest to a seed.

        Args:
            T_target: (N, 4, 4) poses of tool0 in the base frame, mm.
            q_seed_deg: (N, 6) or (6,) controller seeds (deg); default ``home_deg`` of the config.
                With the analytic solver the seed picks the branch and the turn of axes 4/6;
                with the numeric one it is the starting point (None: random restarts).

        Returns:
            ``(q_deg, ok)``: (N, 6) controller joints and (N,) bool, True where the pose is
            reached within the tolerances by joints inside the axis ranges.

        Raises:
            RobotInputError: bad shapes, NaN, non-orthonormal rotations.
        """
        sol = self.solve_ik(T_target, q_seed_deg)
        return sol.q_deg, sol.ok

    def solve_ik(self, T_target: Tensor | np.ndarray, q_seed_deg: Tensor | np.ndarray | None = None,
                 method: str | None = None) -> IKSolution:
        """Like :meth:`ik`, with the residuals and the reach/range verdicts separately.

        Args:
            T_target: (N, 4, 4) tool0 poses, mm.
            q_seed_deg: (N, 6) or (6,) seeds, controller degrees.
            method: ``"analytic"`` or ``"numeric"`` (default: ``ik_method`` of the config).
        """
        T = self._poses(T_target).reshape(-1, 4, 4)
        method = method or self.config.ik_method
        if method == "analytic":
            seed = self._seed(q_seed_deg, T.shape[0])
            cand, valid = self.ik_candidates(T, seed)
            q, _ = self.select_nearest(cand, valid, seed)
        elif method == "numeric":
            q, seed = self._ik_numeric(T, q_seed_deg)
            one = torch.ones(q.shape[0], 1, dtype=torch.bool, device=self.device)
            q, _ = self.select_nearest(q[:, None], one, seed)
        else:
            raise RobotInputError(f"method: expected 'analytic' or 'numeric', got {method!r}")
        return self._verify(T, q)

    def ik_path(self, T_target: Tensor | np.ndarray, q_start_deg: Tensor | np.ndarray | None = None
                ) -> IKSolution:
        """IK along a path, each pose seeded from its neighbour's solution (analytic).

        All candidate solutions are computed in one batch; the branch and the axis turns are
        then chosen pose by pose, nearest to the previous pose's joints (the first one nearest
        ``q_start_deg``, default ``home_deg``). An unreachable pose keeps the previous seed.

        Args:
            T_target: (N, 4, 4) tool0 poses along the path, mm.
            q_start_deg: (6,) joints the path starts from (controller degrees).

        Returns:
            :class:`IKSolution` over the N poses.
        """
        T = self._poses(T_target).reshape(-1, 4, 4)
        seed0 = to_numpy(self._seed(q_start_deg, 1))
        Tn = to_numpy(T).astype(float)
        cand, valid = arm_candidates(np, self.geometry, Tn, np.broadcast_to(seed0, (len(Tn), 6)))
        q = self._selector(cand, valid).pick_sequential(seed0[0])
        return self._verify(T, torch.as_tensor(q, dtype=self.dtype, device=self.device))

    def _verify(self, T: Tensor, q: Tensor) -> IKSolution:
        """Residuals of ``q`` against ``T`` with the chain's FK: the one judge of 'reached'."""
        Tq = self.fk(q)
        pos = (Tq[:, :3, 3] - T[:, :3, 3]).norm(dim=-1)
        rot = torch.rad2deg(rotation_angle(Tq[:, :3, :3], T[:, :3, :3]))
        tol = self.config.ik
        reached = (pos <= tol.position_tol_mm) & (rot <= tol.orientation_tol_deg)
        return IKSolution(q, reached, self.in_range(q), pos, rot)

    def wrist_centre(self, T_flange: Tensor) -> Tensor:
        """(N, 3) wrist centre (axes 4, 5, 6 meet) of tool0 poses (N, 4, 4), mm."""
        g = self.geometry
        R6 = T_flange[:, :3, :3] @ _const(torch, g.R0, T_flange).T  # link_6 orientation
        return T_flange[:, :3, 3] - g.d6 * R6[:, :, 0]

    def ik_candidates(self, T_target: Tensor, q_seed_deg: Tensor | None = None
                      ) -> tuple[Tensor, Tensor]:
        """All 8 closed-form solutions (front/back x elbow x wrist flip) of tool0 poses.

        Args:
            T_target: (N, 4, 4) tool0 poses, mm (not re-validated: use :meth:`solve_ik`).
            q_seed_deg: (N, 6) seeds; only used where the solution is a continuum (axis 1 with
                the wrist centre on axis 1, axes 4 + 6 with axis 5 at 0): the seed's value is
                kept for axis 1 / axis 4.

        Returns:
            ``(q_deg, valid)``: (N, 8, 6) controller joints, each in [-180, 180), and (N, 8)
            bool, False where the wrist centre is out of the arm's reach for that branch.
        """
        T = torch.as_tensor(T_target, dtype=self.dtype, device=self.device)
        seed = (torch.zeros(T.shape[0], 6, dtype=self.dtype, device=self.device)
                if q_seed_deg is None else q_seed_deg)
        return arm_candidates(torch, self.geometry, T, seed)

    # ------------------------------------------------------------------ branch choice
    def select_nearest(self, cand_deg: Tensor, valid: Tensor, seed_deg: Tensor
                       ) -> tuple[Tensor, Tensor]:
        """Pick, per goal, the candidate nearest the seed, preferring ones inside the ranges.

        Each axis may be turned by +-360 deg (axis 6 spans 600 deg); per axis the turn inside
        the range and nearest the seed is used. Candidates are then ranked by the number of axes
        out of range, then by the squared distance (deg^2) to the seed.

        Args:
            cand_deg: (N, C, 6) candidate controller joints.
            valid: (N, C) candidates that exist.
            seed_deg: (N, 6) seeds.

        Returns:
            ``(q_deg, index)``: (N, 6) chosen joints (the seed where no candidate is valid) and
            (N,) chosen candidate index (-1 where none is valid).
        """
        sel = self._selector(to_numpy(cand_deg), to_numpy(valid))
        q, idx = sel.pick(to_numpy(seed_deg))
        return (torch.as_tensor(q, dtype=self.dtype, device=self.device),
                torch.as_tensor(idx, device=self.device))

    def _selector(self, cand: np.ndarray, valid: np.ndarray) -> _Selector:
        ax = self.config.axes
        return _Selector(cand, valid, np.asarray(ax.min_deg, float), np.asarray(ax.max_deg, float),
                         self.config.axis3_range_applies_to == "difference")

    def _select_sequential(self, cand: Tensor, valid: Tensor, seed0: Tensor) -> Tensor:
        q = self._selector(to_numpy(cand), to_numpy(valid)).pick_sequential(to_numpy(seed0))
        return torch.as_tensor(q, dtype=self.dtype, device=self.device)

    # ------------------------------------------------------------------ numeric IK
    def _ik_numeric(self, T: Tensor, q_seed_deg: Tensor | np.ndarray | None
                    ) -> tuple[Tensor, Tensor]:
        """PseudoInverseIK (pytorch-kinematics): seeded (1 start per goal) or random restarts."""
        cfg = self.config.ik
        N = T.shape[0]
        goal = pk.Transform3d(matrix=T / self._mm, dtype=self.dtype, device=self.device)
        # early_stopping_no_improvement="all" can drop every goal (measured: 0 of 100 solved):
        # off. A goal stops once a start converged (warm starts take ~3 iterations, not
        # max_iterations). pk's own limit enforcement (10 clamped refinements) is off:
        # select_nearest turns axes by 360 and the axis ranges (incl. the coupled axis 3) are
        # judged afterwards anyway.
        common = dict(pos_tolerance=cfg.position_tol_mm / 1000.0,
                      rot_tolerance=math.radians(cfg.orientation_tol_deg),
                      max_iterations=cfg.max_iterations, early_stopping_no_improvement=None,
                      early_stopping_any_converged=True, enforce_joint_limits=False)
        if q_seed_deg is not None:
            seed = self._seed(q_seed_deg, N)
            th0 = controller_to_urdf(seed)
            solver = pk.PseudoInverseIK(self.chain, retry_configs=th0[:1], **common)
            solver.initial_config = th0[:, None, :]  # one warm start per goal
        else:
            seed = self.home_deg.expand(N, 6)
            limits = torch.stack([self.chain.low, self.chain.high], dim=-1)
            solver = pk.PseudoInverseIK(self.chain, num_retries=cfg.restarts,
                                        joint_limits=limits, **common)
        sol = solver.solve(goal)
        qs = urdf_to_controller(sol.solutions)                                  # (N, M, 6)
        # best retry: converged and nearest the seed, else the smallest residual
        err = sol.err_pos * 1000.0 + torch.rad2deg(sol.err_rot)
        dist = ((qs - seed[:, None]) ** 2).sum(-1)
        score = torch.where(sol.converged, dist, 1e12 + err)
        best = score.argmin(dim=1)
        q = qs[torch.arange(N, device=self.device), best]
        return torch.rad2deg(_wrap(torch.deg2rad(q))), seed

    # ------------------------------------------------------------------ closed-form FK/Jacobian
    def arm_jacobian(self, q_deg: Tensor) -> Tensor:
        """Closed-form flange Jacobian, same layout as :meth:`jacobian` (tests check they agree).

        Cheaper than the chain's for a single pose; the reachability gate uses it.

        Args:
            q_deg: (N, 6) controller joints, degrees.

        Returns:
            (N, 6, 6): rows mm/rad (linear) and rad/rad (angular), columns controller axes.
        """
        q = self._joints(q_deg).reshape(-1, 6)
        return arm_forward(torch, self.geometry, q)[1]

    def arm_fk(self, q_deg: Tensor) -> Tensor:
        """Closed-form tool0 pose (N, 4, 4), mm: a cross-check of :meth:`fk`, not a substitute."""
        q = self._joints(q_deg).reshape(-1, 6)
        return arm_forward(torch, self.geometry, q)[0]

    # ------------------------------------------------------------------ geometry
    def _read_geometry(self) -> _ArmGeometry:
        """Arm lengths from the chain at zero, checking the structure the closed form needs."""
        zero = torch.zeros(1, 6, dtype=self.dtype, device=self.device)
        frames = self.chain.forward_kinematics_tensor(zero)[:, 0].detach().cpu().double().numpy()
        idx = {n: int(self.chain.get_frame_indices(n)[0])
               for n in ("link_2", "link_3", "link_4", "link_5", "link_6", EEF_LINK)}
        p = {n: frames[i, :3, 3] * 1000.0 for n, i in idx.items()}
        axes = self.chain.axes.detach().cpu().double().numpy()
        want_axes = np.array([[0, 0, 1], [0, 1, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]])
        rot_ok = all(np.allclose(frames[idx[n], :3, :3], np.eye(3), atol=1e-6)
                     for n in ("link_2", "link_3", "link_4", "link_5", "link_6"))
        a1, d1 = p["link_2"][0], p["link_2"][2]
        g = _ArmGeometry(a1=float(a1), d1=float(d1), a2=float(p["link_3"][2] - d1),
                         a3=float(p["link_5"][2] - p["link_3"][2]),
                         d4=float(p["link_5"][0] - p["link_3"][0]),
                         d6=float(p[EEF_LINK][0] - p["link_5"][0]),
                         R0=frames[idx[EEF_LINK], :3, :3].copy())
        tol = 1e-3  # mm
        lateral = max(abs(p[n][1]) for n in p)
        straight = (abs(p["link_3"][0] - a1) < tol and abs(p["link_4"][2] - p["link_5"][2]) < tol
                    and abs(p[EEF_LINK][2] - p["link_5"][2]) < tol)
        if not (np.allclose(np.abs(axes), want_axes, atol=1e-6) and (axes.sum(-1) > 0).all()
                and rot_ok and lateral < tol and straight):
            raise URDFError(f"{self.urdf_path}: not an IRB 1410-like arm (axes z y y x y x, link "
                            "frames parallel to the base at zero, no lateral offsets, wrist "
                            "centre on axis 4): the closed-form IK does not apply")
        return g


# --------------------------------------------------------------------------- closed form
# Written against the array-API names numpy >= 2 and torch share (atan2, acos, concat, stack
# with axis=...), so the same code runs batched in torch and, for one pose, in numpy, where
# it is several times faster (the live gate checks one pose per frame, within its 1 ms).

def load_irb1410(path: str | os.PathLike[str] | None = None,
                 urdf_path: str | os.PathLike[str] | None = None,
                 dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu"
                 ) -> IRB1410:
    """The shipped arm (the model): :class:`IRB1410` with ``configs/robot.yaml`` (or
    ``path``), read by :func:`~torchseam.robot.config.load_robot_config` (the config; a bad
    file: ``ConfigError`` naming the field). For the command line and scripts; library code
    takes the model as an argument."""
    return IRB1410(load_robot_config(path), urdf_path, dtype, device)


def to_numpy(x: Tensor | np.ndarray) -> np.ndarray:
    """``x`` as a numpy array (a tensor detached and moved to the CPU first)."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _const(xp: ModuleType, value: Any, ref: Array) -> Array:
    if xp is torch:
        return torch.as_tensor(value, dtype=ref.dtype, device=ref.device)
    return np.asarray(value, dtype=ref.dtype)


def _wrap_xp(xp: ModuleType, a: Array) -> Array:
    return xp.remainder(a + math.pi, 2 * math.pi) - math.pi


def _stack(xp: ModuleType, arrays: list[Array], axis: int) -> Array:
    """``xp.stack``; for numpy by assignment (faster than np.stack on tiny arrays)."""
    if xp is torch:
        return torch.stack(arrays, dim=axis)
    first = arrays[0]
    ax = axis % (first.ndim + 1)
    out = np.empty(first.shape[:ax] + (len(arrays),) + first.shape[ax:], dtype=first.dtype)
    lead = (slice(None),) * ax
    for i, a in enumerate(arrays):
        out[lead + (i,)] = a
    return out


def arm_candidates(xp: ModuleType, g: _ArmGeometry, T: Array, seed_deg: Array
                   ) -> tuple[Array, Array]:
    """Closed-form IK of tool0 poses (N, 4, 4) mm: ((N, 8, 6) controller deg, (N, 8) valid).

    ``xp`` is ``numpy`` or ``torch``; see :meth:`IRB1410.ik_candidates`.
    """
    N = T.shape[0]
    seed = xp.deg2rad(seed_deg)
    R0 = _const(xp, g.R0, T)
    R6 = T[:, :3, :3] @ R0.T                      # link_6 orientation
    w = T[:, :3, 3] - g.d6 * R6[:, :, 0]          # wrist centre
    # axis 1: face the wrist centre, or turn away from it (back-bend); on axis 1: keep the seed.
    on_axis = xp.hypot(w[:, 0], w[:, 1]) <= 1e-9
    q1a = xp.where(on_axis, seed[:, 0], xp.atan2(w[:, 1], w[:, 0]))
    q1 = _stack(xp, [q1a, _wrap_xp(xp, q1a + math.pi)], 1)                # (N, 2)
    u = xp.cos(q1) * w[:, :1] + xp.sin(q1) * w[:, 1:2] - g.a1                 # (N, 2)
    v = w[:, 2:3] - g.d1 + 0.0 * u
    c = (u * u + v * v - g.a2**2 - g.L3**2) / (2 * g.a2 * g.L3)
    reach = xp.abs(c) <= 1.0 + 1e-12
    ac = xp.acos(xp.clip(c, -1.0, 1.0))
    th3 = _stack(xp, [ac - g.phi, -ac - g.phi], -1)                        # (N, 2, 2)
    w0u = g.a3 * xp.sin(th3) + g.d4 * xp.cos(th3)
    w0v = g.a2 + g.a3 * xp.cos(th3) - g.d4 * xp.sin(th3)
    th2 = _wrap_xp(xp, xp.atan2(w0v, w0u) - xp.atan2(v, u)[..., None])
    beta = _wrap_xp(xp, th2 + th3)     # controller axis 3: the forearm's angle
    q1e = q1[..., None] + 0.0 * beta
    # The wrist: R03^T R6 = Rx(a4) Ry(a5) Rx(a6) =: M, R03 = Rz(q1) Ry(beta) with columns
    # x3 = (c1 cb, s1 cb, -sb), y3 = (-s1, c1, 0), z3 = (c1 sb, s1 sb, cb). Only 7 entries of M
    # are needed; as dot products they cost a few element-wise ops and no 3x3 products.
    c1, s1 = xp.cos(q1)[..., None], xp.sin(q1)[..., None]                     # (N, 2, 1)
    cb, sb = xp.cos(beta), xp.sin(beta)                                       # (N, 2, 2)

    def rows(j: int) -> tuple[Array, Array, Array]:
        """Rz(q1)^T applied to column j of R6: its x, y (= y3 . r) and z parts, (N, 2, 1)."""
        rx, ry, rz = R6[:, None, None, 0, j], R6[:, None, None, 1, j], R6[:, None, None, 2, j]
        return c1 * rx + s1 * ry, c1 * ry - s1 * rx, rz

    a0, b0, z0 = rows(0)
    a1, b1, z1 = rows(1)
    a2, _, z2 = rows(2)
    m00, m10, m20 = cb * a0 - sb * z0, b0 + 0.0 * cb, sb * a0 + cb * z0
    m01, m02 = cb * a1 - sb * z1, cb * a2 - sb * z2
    m11, m21 = b1 + 0.0 * cb, sb * a1 + cb * z1
    s5 = xp.hypot(m10, m20)
    a5 = xp.atan2(s5, m00)
    regular = s5 > 1e-10
    seed4 = seed[:, 3, None, None] + 0.0 * a5
    a4 = xp.where(regular, xp.atan2(m10, -m20), seed4)
    a6 = xp.where(regular, xp.atan2(m01, m02), xp.atan2(m21, m11) - seed4)
    ok_wrist = regular | (m00 > 0)  # a5 = 180 deg: no closed form, far out of range
    arm = _stack(xp, [q1e, th2, beta], -1)                                 # (N, 2, 2, 3)
    wrist1 = _stack(xp, [a4, a5, a6], -1)
    wrist2 = _stack(xp, [a4 + math.pi, -a5, a6 + math.pi], -1)             # the wrist flip
    q = _stack(xp, [xp.concat([arm, wrist1], -1), xp.concat([arm, wrist2], -1)], 3)
    valid = xp.broadcast_to((reach[..., None] & ok_wrist)[..., None], (N, 2, 2, 2))
    return xp.rad2deg(_wrap_xp(xp, q)).reshape(N, 8, 6), valid.reshape(N, 8)


def arm_forward(xp: ModuleType, g: _ArmGeometry, q_deg: Array, tool: Array | None = None
                ) -> tuple[Array, Array]:
    """Closed-form tool0 pose (N, 4, 4) mm and flange Jacobian (N, 6, 6) of controller joints.

    Jacobian rows: mm/rad (linear), rad/rad (angular); columns: controller axes 1..6. Built from
    axis directions and points only (few, vectorised ops: it is the live gate's inner loop).
    With ``tool`` (4, 4) mm in the flange frame: the TCP's pose and Jacobian instead (the same
    angular rows; the linear ones of the TCP point, axis 6 included), in the same few ops.
    """
    q = xp.deg2rad(q_deg)
    c, s = xp.cos(q), xp.sin(q)
    c1, s1, c2, s2, cb, sb = c[:, 0], s[:, 0], c[:, 1], s[:, 1], c[:, 2], s[:, 2]
    c4, s4, c5, s5, c6, s6 = c[:, 3], s[:, 3], c[:, 4], s[:, 4], c[:, 5], s[:, 5]
    zero, one = xp.zeros_like(c1), xp.ones_like(c1)

    def vec(x: Array, y: Array, z: Array) -> Array:
        return _stack(xp, [x, y, z], -1)

    z1 = vec(zero, zero, one)                   # axis 1
    y1 = vec(-s1, c1, zero)                     # axes 2 and 3 (parallel)
    x3 = vec(c1 * cb, s1 * cb, -sb)             # forearm = axis 4; its angle is axis 3
    z3 = vec(c1 * sb, s1 * sb, cb)
    p2 = vec(g.a1 * c1, g.a1 * s1, g.d1 + zero)
    p3 = p2 + g.a2 * vec(c1 * s2, s1 * s2, c2)  # link 2 turned by axis 2
    pw = p3 + g.d4 * x3 + g.a3 * z3             # wrist centre
    y4 = c4[:, None] * y1 + s4[:, None] * z3    # axis 5
    z4 = c4[:, None] * z3 - s4[:, None] * y1
    x5 = c5[:, None] * x3 - s5[:, None] * z4    # axis 6
    z5 = s5[:, None] * x3 + c5[:, None] * z4
    y6 = c6[:, None] * y4 + s6[:, None] * z5
    z6 = c6[:, None] * z5 - s6[:, None] * y4
    pe = pw + g.d6 * x5                         # flange
    R6 = _stack(xp, [x5, y6, z6], -1) @ _const(xp, g.R0, q)
    pt = pe                                     # the point the linear rows are of
    if tool is not None:
        tool = _const(xp, tool, q)
        pt, R6 = pe + R6 @ tool[:3, 3], R6 @ tool[:3, :3]
    # columns: axis 2 translates the forearm (parallelogram); axis 6 moves only a TCP off it
    axes = _stack(xp, [z1, y1, y1, x3, y4, x5], 1)                          # (N, 6, 3)
    lin = cross(axes, _stack(xp, [pt, p3 - p2, pt - p3, pt - pw, pt - pw, pt - pe], 1))
    ang = _stack(xp, [z1, xp.zeros_like(z1), y1, x3, y4, x5], 1)
    J = xp.swapaxes(xp.concat([lin, ang], 2), 1, 2)
    bottom = xp.broadcast_to(_const(xp, [[0.0, 0.0, 0.0, 1.0]], q), (q.shape[0], 1, 4))
    T = xp.concat([xp.concat([R6, pt[:, :, None]], -1), bottom], 1)
    return T, J


def range_excess(q_deg: Array, lo: Array, hi: Array, axis3_difference: bool) -> Array:
    """How far each axis lies outside [lo, hi] (deg): 0 inside, > 0 above, < 0 below (numpy or
    torch). With ``axis3_difference`` axis 3 is judged on ``axis3 - axis2``."""
    v = checked_values(q_deg, axis3_difference)
    if isinstance(v, torch.Tensor):
        return torch.clamp(v - hi, min=0.0) + torch.clamp(v - lo, max=0.0)
    return np.maximum(v - hi, 0.0) + np.minimum(v - lo, 0.0)  # np.clip is slow on tiny arrays


def checked_values(q_deg: Array, axis3_difference: bool) -> Array:
    """The values the axis ranges apply to: controller joints, axis 3 maybe as axis3 - axis2."""
    if not axis3_difference:
        return q_deg
    xp = torch if isinstance(q_deg, torch.Tensor) else np
    return xp.concat([q_deg[..., :2], q_deg[..., 2:3] - q_deg[..., 1:2], q_deg[..., 3:]], axis=-1)


_TURNS = np.array([0.0, -360.0, 360.0])


class _Selector:
    """Choice among IK candidates (numpy): per axis the +-360 turn inside the range and nearest
    the seed, then the candidate with the fewest axes out of range, then nearest the seed."""

    def __init__(self, cand: np.ndarray, valid: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 axis3_difference: bool) -> None:
        alt = cand[..., None] + _TURNS                                          # (N, C, 6, 3)
        inside = (alt >= lo[:, None] - 1e-9) & (alt <= hi[:, None] + 1e-9)
        if axis3_difference:  # axis 3's range moves with axis 2 (never turned: +-70 deg)
            a2 = cand[..., 1:2]
            inside[..., 2, :] = ((alt[..., 2, :] - a2 >= lo[2] - 1e-9)
                                 & (alt[..., 2, :] - a2 <= hi[2] + 1e-9))
        self.alt = alt
        self.pen = np.where(inside, 0.0, 1e6)
        self.inval = np.where(valid, 0.0, 1e12)
        self.any = np.asarray(valid.any(axis=1))  # (N,) poses with a valid solution

    def pick(self, seed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Batched: (N, 6) seeds -> (N, 6) joints, (N,) index (-1: none valid, seed kept)."""
        N, C = self.alt.shape[:2]
        n, c, a = np.ogrid[:N, :C, :6]  # plain fancy indexing: take_along_axis is slow here
        k = (np.abs(self.alt - seed[:, None, :, None]) + self.pen).argmin(axis=-1)
        q = self.alt[n, c, a, k]                                               # (N, C, 6)
        score = self.pen[n, c, a, k].sum(-1) + ((q - seed[:, None]) ** 2).sum(-1) + self.inval
        idx = score.argmin(axis=1)
        chosen = q[np.arange(N), idx]
        return np.where(self.any[:, None], chosen, seed), np.where(self.any, idx, -1)

    def pick_sequential(self, seed0: np.ndarray) -> np.ndarray:
        """Pose i is seeded from pose i-1's choice (the first from ``seed0`` (6,))."""
        alt, pen, inval = self.alt, self.pen, self.inval
        C = alt.shape[1]
        ci, ai = np.arange(C)[:, None], np.arange(6)[None, :]
        out = np.empty(alt.shape[:1] + (6,))
        prev = np.asarray(seed0, dtype=float).reshape(6)
        for i in range(alt.shape[0]):  # sequential by nature: each pose seeds the next
            a, p = alt[i], pen[i]
            k = (np.abs(a - prev[:, None]) + p).argmin(axis=-1)                # (C, 6)
            q = a[ci, ai, k]
            j = int((p[ci, ai, k].sum(-1) + ((q - prev) ** 2).sum(-1) + inval[i]).argmin())
            out[i] = q[j]
            if self.any[i]:
                prev = out[i]
            else:
                out[i] = prev
        return out
