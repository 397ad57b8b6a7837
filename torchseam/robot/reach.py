"""Reachability gate: may the IRB 1410 move the torch through these TCP poses?

Every pose is checked before it reaches the controller, in this order (a refused pose carries
every reason that applies, the first one as its :class:`Reason` code):

1. **IK**: the tool transform of ``configs/cell.yaml`` turns the torch TCP pose into a flange
   (tool0) pose; the closed-form IK gives all branches, and along a sequence each pose takes the
   solution nearest its neighbour's (the first one nearest a start/home configuration).
2. **Axis ranges**, with the coupled axis-3 check of ``configs/robot.yaml``.
3. **Singularity margin**: smallest singular value of the flange Jacobian.
4. **Joint speed** between consecutive poses, at the time between them (explicit, or the TCP
   distance at the cell's weld speed but at least one camera frame), against the axis speeds
   times a safety factor. It is measured from the previous pose that passed the other checks
   (a refused pose is not where the robot will be).
5. **Torch-vs-part clearance**: the torch body lies along the TCP z axis (the tip's last mm
   excluded: it touches the seam by design), a cylinder, or with a nozzle
   (``configs/robot.yaml`` torch) a cone from the nozzle's front widening to the body's
   radius, then the cylinder; the main pipe is its oval cross-section (an
   elliptic cylinder with flat ends, semi-axes from ``main_ovality``), the branch a capsule
   around its axis, from the part configuration and its nominal placement. On the other kinds
   of part (:mod:`torchseam.core.part`) the main body is the plate (a box) or the sphere.

Batched (:meth:`ReachGate.check`) for a whole seam, or one pose at a time
(:meth:`ReachGate.step`, which keeps the last accepted joints) for the live loop; a gate is also
the callable ``gate(position_mm, quaternion) -> (ok, reason)`` the EGM link takes.

Example:
    >>> from torchseam.core.config import load_cell, load_part
    >>> from torchseam.robot.kinematics import load_irb1410
    >>> gate = ReachGate(load_irb1410(), cell=load_cell(), part=load_part())
    >>> T = nominal_torch_poses(load_part(), 360)
    >>> result = gate.check(T)
    >>> result.ok.shape
    torch.Size([360])
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
import torch

from torchseam.core.config import CellConfig, PartConfig
from torchseam.core.part import make_joint, torch_frames
from torchseam.core.transforms import pose_matrix
from torchseam.robot.kinematics import (
    IRB1410,
    RobotInputError,
    Tensor,
    arm_candidates,
    arm_forward,
    checked_values,
    range_excess,
    rotation_angle,
    validate_poses,
)
from torchseam.robot.kinematics import to_numpy as _np

__all__ = ["Reason", "ReachResult", "PoseVerdict", "ReachGate", "nominal_torch_poses"]


class Reason(str, Enum):
    """Why a pose was refused (the first failing check), ``OK`` when it was not."""

    OK = "ok"
    UNREACHABLE = "unreachable"
    AXIS_RANGE = "axis range"
    SINGULARITY = "singularity"
    JOINT_SPEED = "joint speed"
    CLEARANCE = "clearance"


@dataclass(frozen=True)
class ReachResult:
    """Verdicts for N poses (tensors on the robot's device and dtype).

    Attributes:
        ok: (N,) bool, the pose passed every check.
        q_deg: (N, 6) controller joints of the chosen IK solution (meaningless where
            ``code`` is ``UNREACHABLE``).
        code: N :class:`Reason` codes, ``Reason.OK`` where ok.
        reasons: N messages, ``""`` where ok, e.g. ``"axis 5 out of range (121.3 > 115)"``;
            several failing checks are joined with ``"; "``.
        sigma_min: (N,) smallest singular value of the scaled flange Jacobian.
        speed_ratio: (N,) worst axis speed / allowed speed, from the previous pose that passed
            the other checks (0 for the first pose).
        clearance_mm: (N,) smallest torch-to-pipe clearance (``inf`` without a part).
    """

    ok: Tensor
    q_deg: Tensor
    code: tuple[Reason, ...]
    reasons: tuple[str, ...]
    sigma_min: Tensor
    speed_ratio: Tensor
    clearance_mm: Tensor

    def __len__(self) -> int:
        return len(self.code)

    def summary(self) -> str:
        """One line: ``"360 poses: 357 ok, 3 refused (joint speed 2, clearance 1)"``."""
        n_ok = int(self.ok.sum())
        counts: dict[str, int] = {}
        for c in self.code:
            if c is not Reason.OK:
                counts[c.value] = counts.get(c.value, 0) + 1
        tail = f" ({', '.join(f'{k} {v}' for k, v in counts.items())})" if counts else ""
        return f"{len(self)} poses: {n_ok} ok, {len(self) - n_ok} refused{tail}"


@dataclass(frozen=True)
class PoseVerdict:
    """Verdict for one pose (:meth:`ReachGate.step`)."""

    ok: bool
    q_deg: np.ndarray   # (6,) controller joints
    code: Reason
    reason: str


@dataclass(frozen=True)
class _Verdicts:  # numpy side of ReachResult
    code: tuple[Reason, ...]
    reasons: tuple[str, ...]
    q: np.ndarray
    sigma: np.ndarray
    ratio: np.ndarray
    clearance: np.ndarray


class ReachGate:
    """Batched reachability gate for torch TCP poses in the robot base frame (mm).

    Args:
        robot: the kinematic model; its config holds the gate's limits
            (:func:`~torchseam.robot.kinematics.load_irb1410`: the shipped one).
        cell: tool transform (TCP in flange) and weld speed (``configs/cell.yaml``:
            :func:`~torchseam.core.config.load_cell`).
        part: the work piece for the clearance check; ``None`` skips that check.
        part_pose_mm: (4, 4) pose of the joint frame {T} in the base; default the part's nominal
            ``placement`` (the clamping error is unknown to the planner).

    Example:
        >>> from torchseam.core.config import load_cell
        >>> from torchseam.robot.kinematics import load_irb1410
        >>> gate = ReachGate(load_irb1410(), cell=load_cell())
        >>> T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        >>> T[:, :3, 3] = torch.tensor([[2000.0, 0, 500], [900.0, 0, 800]])
        >>> gate.check(T).code[0]
        <Reason.UNREACHABLE: 'unreachable'>
    """

    def __init__(self, robot: IRB1410, *, cell: CellConfig, part: PartConfig | None = None,
                 part_pose_mm: np.ndarray | None = None) -> None:
        self.robot = robot
        self.config = self.robot.config
        self.cell = cell
        self.tool = self.cell.tool.matrix()                   # TCP in flange, (4, 4) mm
        self.tool_inv = np.linalg.inv(self.tool)
        self.weld_speed_mm_s = float(self.cell.process.weld_speed_mm_s)
        # the tracker makes at most one pose per camera frame: the shortest time between poses
        self.min_dt_s = 1.0 / float(self.cell.process.frame_rate_hz)
        ax = self.config.axes
        self.allowed_speed = np.asarray(ax.max_speed_deg_s) * ax.speed_safety_factor
        self._lo = np.asarray(ax.min_deg, dtype=float)
        self._hi = np.asarray(ax.max_deg, dtype=float)
        self.part = part
        self._pipes = (_part_solids(part, part_pose_mm, self.config.clearance.main_pipe_length_mm)
                       if part is not None else None)
        self._scale = np.ones((6, 1))
        self._scale[:3] = 1.0 / self.config.singularity.length_mm
        self._q_prev: np.ndarray | None = None
        self._p_prev: np.ndarray | None = None
        self._last_ok: tuple[np.ndarray, np.ndarray] | None = None  # (p, q) last passed by __call__
        # (p, q, reference, verdict) of :meth:`prepare`, for the __call__ that follows
        self._pending: tuple[np.ndarray, np.ndarray, tuple, PoseVerdict] | None = None

    # ------------------------------------------------------------------ batch
    def check(self, T_tcp: Tensor | np.ndarray, *, q_start_deg: Tensor | np.ndarray | None = None,
              dt_s: float | Tensor | np.ndarray | None = None) -> ReachResult:
        """Check a sequence of torch TCP poses along a seam.

        IK runs along the sequence (each pose seeded from its neighbour, see
        :meth:`IRB1410.ik_path`) and every answer is verified with the chain's FK.

        Args:
            T_tcp: (N, 4, 4) torch TCP poses in the base frame, mm, in path order.
            q_start_deg: (6,) joints to seed the first pose from (default ``home_deg``).
            dt_s: time between consecutive poses, seconds: a number, or (N,) where ``dt_s[i]``
                is the time from pose i-1 to pose i (``dt_s[0]`` unused). Default: TCP distance
                over the cell's weld speed, at least one camera frame (``1 / frame_rate_hz``).

        Returns:
            :class:`ReachResult` over the N poses.

        Raises:
            RobotInputError: bad shapes, NaN, non-rigid poses, bad ``dt_s``.
        """
        robot = self.robot
        T = robot._poses(T_tcp, "T_tcp").reshape(-1, 4, 4)
        tool_inv = torch.as_tensor(self.tool_inv, dtype=robot.dtype, device=robot.device)
        sol = robot.ik_path(T @ tool_inv, q_start_deg)
        Tn = _np(T).astype(float)
        dt = self._dt(Tn, dt_s)
        v = self._judge(Tn, _np(sol.q_deg), _np(sol.reached), _np(sol.pos_err_mm),
                        _np(sol.rot_err_deg), dt, None)

        def out(a: np.ndarray) -> Tensor:
            return torch.as_tensor(a, dtype=robot.dtype, device=robot.device)

        return ReachResult(torch.tensor([c is Reason.OK for c in v.code], device=robot.device),
                           sol.q_deg, v.code, v.reasons, out(v.sigma), out(v.ratio),
                           out(v.clearance))

    # ------------------------------------------------------------------ incremental
    def reset(self, q_deg: Tensor | np.ndarray | None = None,
              tcp_position_mm: np.ndarray | None = None) -> None:
        """Forget the previous pose; optionally start from known joints / TCP position."""
        self._q_prev = None if q_deg is None else _np(self.robot._joints(q_deg).reshape(6)).copy()
        self._p_prev = None if tcp_position_mm is None else np.asarray(tcp_position_mm, float)
        self._last_ok = None
        self._pending = None

    def step(self, T_tcp: Tensor | np.ndarray, dt_s: float | None = None) -> PoseVerdict:
        """Check the next pose of a live sequence against the last accepted one.

        The IK is seeded from the last accepted joints (``home_deg`` before the first); the
        joint speed is checked over ``dt_s`` (default: TCP distance / weld speed, at least one
        camera frame). An accepted
        pose becomes the new reference, a refused one does not. Runs in numpy with the
        closed-form kinematics (checked against the chain in the tests): well under 1 ms.

        Args:
            T_tcp: (4, 4) torch TCP pose in the base frame, mm.
            dt_s: seconds since the last accepted pose.
        """
        self._last_ok = None  # the reference may move: __call__'s shortcut must not outlive it
        T = _np(T_tcp).astype(float)
        validate_poses(T, "T_tcp")
        T = T.reshape(-1, 4, 4)
        if T.shape[0] != 1:
            raise RobotInputError(f"T_tcp: step() takes one pose, got {T.shape[0]}")
        robot, g = self.robot, self.robot.geometry
        seed = (np.asarray(self.config.home_deg, float) if self._q_prev is None
                else self._q_prev)[None]
        T_fl = T @ self.tool_inv
        cand, valid = arm_candidates(np, g, T_fl, seed)
        q, idx = robot._selector(cand, valid).pick(seed)
        T_q, J = arm_forward(np, g, q)
        pos = np.linalg.norm(T_q[:, :3, 3] - T_fl[:, :3, 3], axis=-1)
        rot = np.rad2deg(rotation_angle(T_q[:, :3, :3], T_fl[:, :3, :3]))
        tol = self.config.ik
        reached = (idx >= 0) & (pos <= tol.position_tol_mm) & (rot <= tol.orientation_tol_deg)
        p = T[0, :3, 3]
        if dt_s is None:
            dist = 0.0 if self._p_prev is None else float(np.linalg.norm(p - self._p_prev))
            dt_s = max(dist / self.weld_speed_mm_s, self.min_dt_s)
        v = self._judge(T, q, reached, pos, rot, np.array([float(dt_s)]), self._q_prev, J)
        ok = v.code[0] is Reason.OK
        if ok:
            self._q_prev, self._p_prev = q[0].copy(), p.copy()
        return PoseVerdict(ok, q[0], v.code[0], v.reasons[0])

    def _reference(self) -> tuple:
        """What a verdict depends on besides the pose: the last accepted joints and TCP."""
        return tuple(None if a is None else a.copy() for a in (self._q_prev, self._p_prev))

    def _ready_for(self, p: np.ndarray, q: np.ndarray) -> bool:
        """prepare() checked this very pose from the present reference."""
        pend = self._pending
        return pend is not None and np.array_equal(p, pend[0]) and np.array_equal(
            q, pend[1]) and _same(pend[2], self._reference())

    @staticmethod
    def _pose_args(position_mm: np.ndarray, quaternion: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, str]:
        p = np.asarray(position_mm, dtype=float).reshape(3)
        q = np.asarray(quaternion, dtype=float).reshape(4)
        if not (np.isfinite(p).all() and np.isfinite(q).all()):
            return p, q, "pose is not finite"
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            return p, q, f"quaternion norm {norm:.6f} is not 1"
        return p, q, ""

    def prepare(self, position_mm: np.ndarray, quaternion: np.ndarray) -> None:
        """Check a pose ahead of time (the live loop does it between camera frames) without
        making it the reference: the :meth:`__call__` with the very same pose that follows,
        from the same reference joints, then takes this verdict instead of running the IK and
        checks (~1.3 ms) on the control path. The verdict is the one :meth:`step` would give
        then (same pose, same reference: the checks depend on nothing else); a different pose
        or a moved reference is checked afresh."""
        p, q, bad = self._pose_args(position_mm, quaternion)
        if bad:
            return
        if self._ready_for(p, q):
            return  # checked already
        kept = (self._q_prev, self._p_prev, self._last_ok)
        try:
            v = self.step(pose_matrix(p, q / np.linalg.norm(q)))
        finally:
            self._q_prev, self._p_prev, self._last_ok = kept  # a dry run: the reference stays
        self._pending = (p.copy(), q.copy(), self._reference(), v)

    def __call__(self, position_mm: np.ndarray, quaternion: np.ndarray) -> tuple[bool, str]:
        """EGM gate interface: ``(ok, reason)`` for a TCP pose (mm, quaternion w, x, y, z)."""
        p, q, bad = self._pose_args(position_mm, quaternion)
        if bad:
            return False, bad
        if self._last_ok is not None and np.array_equal(p, self._last_ok[0]) and np.array_equal(
                q, self._last_ok[1]):
            # the live loop re-sends its current target every frame to feed the watchdog:
            # the same pose from the same joints gives the same verdict (zero joint motion),
            # so the IK and checks (about 1 ms) are not run again
            return True, ""
        pend = self._pending
        if pend is not None and self._ready_for(p, q):
            v = pend[3]  # checked by prepare() from this very reference
            self._pending = None
            if v.ok:
                self._q_prev, self._p_prev = v.q_deg.copy(), p.copy()
        else:
            v = self.step(pose_matrix(p, q / np.linalg.norm(q)))
        self._last_ok = (p.copy(), q.copy()) if v.ok else None
        return v.ok, v.reason

    # ------------------------------------------------------------------ the checks
    def _dt(self, T: np.ndarray, dt_s: float | Tensor | np.ndarray | None) -> np.ndarray:
        n = T.shape[0]
        if dt_s is None:
            step = np.linalg.norm(T[1:, :3, 3] - T[:-1, :3, 3], axis=-1) / self.weld_speed_mm_s
            step = np.maximum(step, self.min_dt_s)
            return np.concatenate([[0.0], step])
        dt = (np.asarray(dt_s, dtype=float) if isinstance(dt_s, float | int)
              else _np(dt_s).astype(float))
        if dt.ndim == 0:
            dt = np.full(n, float(dt))
        if dt.shape != (n,):
            raise RobotInputError(f"dt_s: expected a number or shape ({n},), got {dt.shape}")
        if not np.isfinite(dt).all() or (dt < 0).any():
            raise RobotInputError("dt_s: times must be finite and >= 0")
        return dt

    def _judge(self, T: np.ndarray, q: np.ndarray, reached: np.ndarray, pos_err: np.ndarray,
               rot_err: np.ndarray, dt: np.ndarray, q_prev: np.ndarray | None,
               J: np.ndarray | None = None) -> _Verdicts:
        """All checks on N poses (numpy): T (N, 4, 4) TCP, q (N, 6) chosen joints."""
        cfg, g = self.config, self.robot.geometry
        n = T.shape[0]
        msgs: list[list[tuple[Reason, str]]] = [[] for _ in range(n)]

        # 1. unreachable
        for i in np.flatnonzero(~reached):
            msgs[i].append((Reason.UNREACHABLE, self._unreachable(T[i], pos_err[i], rot_err[i])))

        # 2. axis ranges (coupled axis 3 as configured)
        diff = self.robot.axis3_difference
        excess = range_excess(q, self._lo, self._hi, diff)
        values = checked_values(q, diff)
        for i, k in zip(*np.nonzero((np.abs(excess) > 1e-9) & reached[:, None]), strict=True):
            name = "axis 3 - axis 2" if (k == 2 and diff) else f"axis {k + 1}"
            above = excess[i, k] > 0
            lim = self._hi[k] if above else self._lo[k]
            msgs[i].append((Reason.AXIS_RANGE, f"{name} out of range ({values[i, k]:.1f} "
                                               f"{'>' if above else '<'} {lim:g})"))

        # 3. singularity margin: smallest singular value of the scaled flange Jacobian
        if J is None:
            J = arm_forward(np, g, q)[1]
        sigma = np.linalg.svd(J * self._scale, compute_uv=False)[:, -1]
        for i in np.flatnonzero((sigma < cfg.singularity.min_sigma) & reached):
            msgs[i].append((Reason.SINGULARITY, f"near singularity (sigma_min {sigma[i]:.4f} < "
                                                f"{cfg.singularity.min_sigma:g})"))

        # 5. torch vs part
        clear = np.full(n, np.inf)
        collide = np.zeros(n, dtype=bool)
        clear_msgs: list[tuple[int, str]] = []
        if self._pipes is not None:
            per_pipe = self._clearance(T)                                      # (N, P)
            clear = per_pipe.min(axis=1)
            margin = cfg.clearance.margin_mm
            collide = clear < margin
            for i, j in zip(*np.nonzero(per_pipe < margin), strict=True):
                c = per_pipe[i, j]
                name = self._pipes.names[j]
                clear_msgs.append((i, f"torch hits {name} (clearance {c:.1f} mm)"
                                   if c < 0 else f"torch too close to {name} "
                                   f"(clearance {c:.1f} mm < {margin:g})"))

        # 4. joint speed, from the previous pose that passed every other check (a refused pose
        # is not where the robot will be) over the time since it
        static_ok = np.array([not m for m in msgs]) & ~collide
        speed, dq, has_prev = _speeds(q, static_ok, dt, q_prev)
        ratio = (speed / self.allowed_speed).max(axis=-1)
        for i in np.flatnonzero((ratio > 1.0) & reached & has_prev):
            k = int(np.argmax(speed[i] / self.allowed_speed))
            m = (f"joint speed axis {k + 1} {speed[i, k]:.1f} deg/s > "
                 f"{self.allowed_speed[k]:.1f}")
            if dq[i, k] > 180.0:  # not a fast move: the continuous solution left the ranges
                m += (f" (a {dq[i, k]:.0f} deg jump: the continuous solution leaves the axis "
                      "ranges here, the arm would have to change configuration or unwind)")
            msgs[i].append((Reason.JOINT_SPEED, m))
        for row, m in clear_msgs:
            msgs[row].append((Reason.CLEARANCE, m))

        code = tuple(m[0][0] if m else Reason.OK for m in msgs)
        reasons = tuple("; ".join(t for _, t in m) for m in msgs)
        return _Verdicts(code, reasons, q, sigma, ratio, clear)

    def _unreachable(self, T_tcp: np.ndarray, pos_err: float, rot_err: float) -> str:
        g = self.robot.geometry
        T_fl = T_tcp @ self.tool_inv
        w = T_fl[:3, 3] - g.d6 * (T_fl[:3, :3] @ g.R0.T)[:, 0]     # wrist centre
        r, v = math.hypot(w[0], w[1]), w[2] - g.d1
        near = min(math.hypot(r - g.a1, v), math.hypot(-r - g.a1, v))   # front / back-bend
        far = max(math.hypot(r - g.a1, v), math.hypot(-r - g.a1, v))
        lo, hi = abs(g.a2 - g.L3), g.a2 + g.L3
        if near > hi:
            return f"out of reach (wrist centre {near:.1f} mm from axis 2 > arm reach {hi:.1f})"
        if far < lo:
            return f"out of reach (wrist centre {far:.1f} mm from axis 2 < {lo:.1f})"
        return f"no IK solution (residual {pos_err:.3f} mm, {rot_err:.3f} deg)"

    def _clearance(self, T: np.ndarray) -> np.ndarray:
        """(N, 2) clearance (mm) of the torch body to the main body and the branch pipe: the
        smallest over its pieces (:meth:`~torchseam.robot.config.TorchShape.pieces`: the
        nozzle's cone, the body's cylinder), each the distance of its axis from the solid less
        its radius there (a cone is taken as the balls swept along its axis: never less than
        the cone)."""
        tc = self.config.torch
        z, tip = T[:, :3, 2], T[:, :3, 3]
        n = T.shape[0]
        pieces = np.array(tc.pieces(), dtype=float)                             # (P, 4)
        # every piece of every pose in one batch (P * N rows): one pass of the sampling
        d0, d1, r0, r1 = (np.repeat(pieces[:, k], n) for k in range(4))
        tip_p, z_p = np.tile(tip, (len(pieces), 1)), np.tile(z, (len(pieces), 1))
        a, b = tip_p - d0[:, None] * z_p, tip_p - d1[:, None] * z_p
        c = np.stack([self._main_distance(a, b, r0, r1), self._branch_distance(a, b, r0, r1)],
                     axis=1)                                                   # (P * N, 2)
        return c.reshape(len(pieces), n, 2).min(axis=0)

    def tip_clearance(self, T_tcp: np.ndarray) -> np.ndarray:
        """(N,) clearance (mm) to the part of the torch's front, the ``tip_exclusion_mm`` in
        front of its body that the gate leaves out (when welding the tip touches the seam by
        design), taken as a line from the TCP back: what a move with the arc off (the seam
        search) must keep clear as well. ``inf`` without a part."""
        T = np.asarray(T_tcp, float).reshape(-1, 4, 4)
        if self._pipes is None:
            return np.full(len(T), np.inf)
        tip, z = T[:, :3, 3], T[:, :3, 2]
        b = tip - self.config.torch.tip_exclusion_mm * z
        zero = np.zeros(len(T))
        return np.minimum(self._main_distance(tip, b, zero, zero),
                          self._branch_distance(tip, b, zero, zero))

    def _main_distance(self, a: np.ndarray, b: np.ndarray, r0: np.ndarray, r1: np.ndarray
                       ) -> np.ndarray:
        """Clearance of torch pieces along a-b ((M, 3), radius r0 at a to r1 at b, (M,)) to
        the main pipe, plate or sphere."""
        s = self._pipes
        assert s is not None, "the clearance is measured only with a part"
        # the main pipe in its own frame (x along its axis): the torch axis's nearest approach
        a_m, b_m = (a - s.main_origin) @ s.main_rotation, (b - s.main_origin) @ s.main_rotation
        if s.main_kind == "pipe":
            return _segment_oval_distance(a_m, b_m, s.main_a, s.main_b, s.main_half_length,
                                          r0=r0, r1=r1)
        if s.main_kind == "plate":
            return _segment_convex_distance(a_m, b_m, lambda x, y, z: _box_distance(
                x, y, z, s.main_a, s.main_b, s.main_half_length), r0=r0, r1=r1)
        if np.array_equal(r0, r1):
            return _point_segment_distance(np.zeros(3), a_m, b_m) - s.main_a - r0
        return _segment_convex_distance(a_m, b_m, lambda x, y, z: np.sqrt(
            x * x + y * y + z * z) - s.main_a, r0=r0, r1=r1)

    def _branch_distance(self, a: np.ndarray, b: np.ndarray, r0: np.ndarray, r1: np.ndarray
                         ) -> np.ndarray:
        """Clearance of torch pieces along a-b to the branch (a capsule)."""
        s = self._pipes
        assert s is not None, "the clearance is measured only with a part"
        if not s.has_branch:
            return np.full(len(a), np.inf)
        A, B = s.branch_A, s.branch_B
        if np.array_equal(r0, r1):
            return _segment_distance(a, b, A[None], B[None]) - s.branch_r - r0
        d = B - A
        dd = float(d @ d)

        def sdf(x, y, z):
            pts = np.stack([x, y, z], axis=-1)
            t = _unit(((pts - A) @ d) / dd)
            return np.linalg.norm(A + t[..., None] * d - pts, axis=-1) - s.branch_r

        return _segment_convex_distance(a, b, sdf, r0=r0, r1=r1)


def _speeds(q: np.ndarray, ref: np.ndarray, dt: np.ndarray, q_prev: np.ndarray | None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 6) axis speeds (deg/s) and moves (deg) from the previous pose where ``ref`` is True
    (``q_prev`` before the first), and (N,) whether there is such a pose."""
    n = q.shape[0]
    last = np.maximum.accumulate(np.where(ref, np.arange(n), -1))
    prev_idx = np.concatenate([[-1], last[:-1]])
    t = np.cumsum(dt)
    has_prev = prev_idx >= 0
    pi = np.maximum(prev_idx, 0)
    q_ref, elapsed = q[pi], t - t[pi]
    if q_prev is not None:  # before this batch's first reference pose: the given one
        q_ref = np.where(has_prev[:, None], q_ref, q_prev[None])
        elapsed = np.where(has_prev, elapsed, t)
        has_prev = np.ones(n, dtype=bool)
    dq = np.abs(q - q_ref)
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = np.where(dq > 1e-9, dq / elapsed[:, None], 0.0)
    return np.where(has_prev[:, None], speed, 0.0), dq, has_prev


@dataclass(frozen=True)
class _PartSolids:
    """The solids the torch must clear, in the base frame (mm): the main body (main pipe,
    plate or sphere) and the branch."""

    main_origin: np.ndarray     # (3,) on the main pipe's axis / the plate's top / the centre
    main_rotation: np.ndarray   # (3, 3) joint frame axes (x: main pipe axis)
    main_a: float               # main pipe semi-axis along the joint frame's y (sphere: radius;
    main_b: float               # ... along its z         plate: half side along x, then along y)
    main_half_length: float     # (plate: its thickness)
    branch_A: np.ndarray        # (3,) branch axis ends (a capsule: the low end is inside the main
    branch_B: np.ndarray        # body, the high end at the branch's top)
    branch_r: float
    main_kind: str = "pipe"     # "pipe", "plate" or "sphere"
    names: tuple[str, str] = ("main pipe", "branch pipe")
    has_branch: bool = True     # False: a part with no branch pipe (two plates, a coupon)


def _part_solids(part: PartConfig, pose: np.ndarray | None, main_length: float) -> _PartSolids:
    """Main body (oval pipe along x of the joint frame, plate or sphere) and branch capsule,
    placed in the base."""
    joint = make_joint(part)
    P = np.asarray(pose, dtype=float) if pose is not None else part.placement.matrix()
    if P.shape != (4, 4) or not np.isfinite(P).all():
        raise RobotInputError(f"part_pose_mm: expected a finite (4, 4) pose, got {P.shape}")
    R, p = P[:3, :3], P[:3, 3]
    main = joint.main_solid()
    kind = main["kind"]
    dims = {"pipe": lambda: (main["a"], main["b"], main.get("half_length", main_length / 2)),
            "plate": lambda: (main["half"], main.get("half_y", main["half"]),
                              main["thickness"]),
            "sphere": lambda: (main["radius"], main["radius"], 0.0)}[kind]()
    main_a, main_b, half_length = (float(v) for v in dims)
    return _PartSolids(R @ main["origin"] + p, R @ main["rotation"], main_a, main_b, half_length,
                       R @ (joint.o + joint.branch_bottom * joint.d) + p,
                       R @ (joint.o + joint.branch_top * joint.d) + p,
                       float(joint.r * max(joint.k1, joint.k2)), kind,
                       (joint.main_name, "branch pipe"), joint.r > 0.0)


def _oval_distance(x: np.ndarray, y: np.ndarray, z: np.ndarray, a: float, b: float,
                   half_length: float) -> np.ndarray:
    """Signed distance (mm, negative inside) of points (x, y, z) (any shape) in the pipe's frame
    from a solid elliptic cylinder along x: semi-axes ``a`` (y) and ``b`` (z), flat ends at
    ``x = +-half_length``.

    The nearest point of the ellipse is found by Newton's method on its angle t (the point
    (a cos t, b sin t)), started from the angle that is exact for a circle; the pipes are near
    circles (ovality <= 0.1), so three steps reach machine precision (none for a circle).
    """
    t = np.arctan2(a * z, b * y)
    ab = a * a - b * b
    for _ in range(0 if ab == 0.0 else 3):
        c, s = np.cos(t), np.sin(t)
        f = a * y * s - b * z * c - ab * s * c          # half the derivative of the distance^2
        df = a * y * c + b * z * s - ab * (c * c - s * s)
        ok = np.abs(df) > 1e-12
        t = t - np.where(ok, f / np.where(ok, df, 1.0), 0.0)
    d = np.hypot(y - a * np.cos(t), z - b * np.sin(t))
    radial = np.where((y / a) ** 2 + (z / b) ** 2 < 1.0, -d, d)
    axial = np.abs(x) - half_length
    return (np.minimum(np.maximum(radial, axial), 0.0)
            + np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0)))


def _box_distance(x: np.ndarray, y: np.ndarray, z: np.ndarray, half: float, half_y: float,
                  thickness: float) -> np.ndarray:
    """Signed distance (mm, negative inside) of points (x, y, z) in the plate's frame from the
    plate: ``|x| <= half``, ``|y| <= half_y``, ``-thickness <= z <= 0``."""
    q = np.stack([np.abs(x) - half, np.abs(y) - half_y,
                  np.abs(z + thickness / 2) - thickness / 2])
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=0)
    return outside + np.minimum(q.max(axis=0), 0.0)


def _segment_oval_distance(p: np.ndarray, q: np.ndarray, a: float, b: float, half_length: float,
                           samples: int = 17, rounds: int = 3, r0=0.0, r1=0.0) -> np.ndarray:
    """Smallest signed distance of segments p-q ((N, 3) each, in the pipe's frame) from the oval
    pipe of :func:`_oval_distance` (:func:`_segment_convex_distance`)."""
    return _segment_convex_distance(
        p, q, lambda x, y, z: _oval_distance(x, y, z, a, b, half_length), samples, rounds,
        r0, r1)


def _segment_convex_distance(p: np.ndarray, q: np.ndarray, sdf, samples: int = 17,
                             rounds: int = 3, r0=0.0, r1=0.0) -> np.ndarray:
    """Smallest signed distance of segments p-q ((N, 3) each) from a convex solid given by its
    signed distance ``sdf(x, y, z)``, less a radius growing linearly from ``r0`` at p to ``r1``
    at q (numbers or (N,); a cone's clearance; 0: the axis's). The distance from a convex solid
    is convex along a line (and stays so less a linear radius), so the best of ``samples``
    equally spaced points brackets the minimum within two spacings; each round samples that
    bracket again (``rounds`` rounds shrink it (samples - 1) / 2 times each: to 0.3 mm along a
    325 mm torch with the defaults, where the distance is flat)."""
    n = p.shape[0]
    ra, rb = (np.asarray(r, float).reshape(-1, 1) for r in (r0, r1))   # (1 or N, 1)
    lo, hi = np.zeros(n), np.ones(n)
    best = np.full(n, np.inf)
    u = np.linspace(0.0, 1.0, samples)[None]
    rows = np.arange(n)
    for _ in range(rounds):
        t = lo[:, None] + (hi - lo)[:, None] * u                                     # (N, S)
        pts = p[:, None] + t[..., None] * (q - p)[:, None]                           # (N, S, 3)
        d = sdf(pts[..., 0], pts[..., 1], pts[..., 2]) - (ra + (rb - ra) * t)
        k = d.argmin(axis=1)
        best = np.minimum(best, d[rows, k])
        step = (hi - lo) / (samples - 1)
        tk = t[rows, k]
        lo, hi = np.maximum(tk - step, 0.0), np.minimum(tk + step, 1.0)
    return best


def _segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray
                      ) -> np.ndarray:
    """Distance between segments p1-q1 and p2-q2 (broadcast (..., 3)); Ericson, Real-Time
    Collision Detection, 5.1.9. Both segments must have non-zero length."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    f = (d2 * r).sum(-1)
    c = (d1 * r).sum(-1)
    b = (d1 * d2).sum(-1)
    denom = a * e - b * b
    parallel = denom <= 1e-12 * a * e
    s = _unit(np.where(parallel, 0.0, (b * f - c * e) / np.where(parallel, 1.0, denom)))
    t = (b * s + f) / e
    s = np.where(t < 0, _unit(-c / a), np.where(t > 1, _unit((b - c) / a), s))
    t = _unit(t)
    return np.linalg.norm((p1 + s[..., None] * d1) - (p2 + t[..., None] * d2), axis=-1)


def _point_segment_distance(x: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Distance of the point ``x`` (3,) from the segments p-q ((N, 3) each)."""
    d = q - p
    t = _unit(((x - p) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12))
    return np.linalg.norm(p + t[:, None] * d - x, axis=-1)


def _same(a: tuple, b: tuple) -> bool:
    """Two tuples of arrays or None hold the same values."""
    return all((x is None and y is None) or (
        x is not None and y is not None and np.array_equal(x, y))
        for x, y in zip(a, b, strict=True))


def _unit(x: np.ndarray) -> np.ndarray:
    return np.minimum(np.maximum(x, 0.0), 1.0)  # np.clip is slow on tiny arrays


def nominal_torch_poses(part: PartConfig, n: int, *, part_pose_mm: np.ndarray | None = None,
                        phi0: float = 0.0, dtype: torch.dtype = torch.float64) -> Tensor:
    """Torch TCP poses once round the part's seam, for checks, tests and benchmarks.

    The frames are :func:`torchseam.core.part.torch_frames` (tip on the seam, z into the corner
    along the bisector of the surface normals, x along the seam: METHOD.md eq. 29) at ``n``
    equal steps of branch angle from ``phi0``, placed in the base.

    Args:
        part: the joint geometry (its deviations included).
        n: number of poses.
        part_pose_mm: (4, 4) pose of {T} in the base; default the nominal placement.

    Returns:
        (n, 4, 4) TCP poses in the base frame, mm.
    """
    phi = phi0 + np.arange(n) * (2 * np.pi / n)
    P = np.asarray(part_pose_mm, float) if part_pose_mm is not None else part.placement.matrix()
    return torch.as_tensor(P @ torch_frames(make_joint(part).seam(phi)), dtype=dtype)
