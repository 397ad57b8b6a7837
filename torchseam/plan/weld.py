"""The weld plan of a part: where it sits, where the six segments start, the torch's angles.

A cell engineer setting up a pipe joint on the positioner chooses how the part sits (turned on
the table, the positioner tilted, shifted a little), where the six segments of the ring start
(METHOD.md section 6: the positioner turns the part 60 degrees between segments, so every
segment is welded at the same place of the workspace), and the torch's work and travel angles
(and its roll about its own axis) within the process's limits. :func:`plan_weld` makes those
choices with the reachability gate (:class:`~torchseam.robot.reach.ReachGate`, the IRB 1410's
IK, axis ranges, singularity margin, joint speeds and torch-vs-part clearance) in the search:

0. The configured plan (``configs/plan.yaml``: ``segment_start_deg``, ``work_angle_deg``,
   ``travel_angle_deg``; the part file's ``placement``; no roll) is checked first and kept as it
   is when every pose passes.
1. Otherwise every segment start round the ring (``search.segment_start_step_deg`` apart) with
   the configured placement, then
2. if no start clears every pose of all but the clearance refusals with
   ``search.min_joint_margin_deg`` to spare on every axis, the placement: turned on the table
   (``yaw_deg``), tilted (``tilt_deg``; the angle that stands the branch upright is always
   among the candidates), shifted (``shift_mm``), one parameter at a time, with the start
   re-chosen near the best one, until nothing improves.
   Candidates are ranked by the poses refused for other reasons than clearance, then how far
   the worst axis falls short of the margin (the wrist and elbow singularities count as an
   axis: a pose's distance to the gate's ``min_sigma`` in degrees of axis 5 at the wrist
   singularity, :attr:`SegmentVerdict.margin_axis` 7; a plan that grazes the singular band
   passes on the planned path but not on the tracked one), then how far the layout is from
   the configured one (in search steps), then the worst margin. Clearance is left out of
   this rank: it depends on the torch's angles to the part, not on where the part sits.
3. Every segment that still has a refused pose gets its own work and travel angles (a grid
   within the configured limits), then its roll, ranked by the refused poses, the margin's
   shortfall, how far the angles are from the configured ones, and the margin.

The search screens candidates on every ``screen_stride``-th pose; the chosen plan is checked on
every pose (:func:`torchseam.plan.preflight.preflight`).

Poses are torch TCP frames (:func:`torchseam.core.part.torch_frames`: tip on the seam, z into
the corner along the bisector, x along the seam) at ``step_mm`` steps of arc length along the
seam of the part as its file describes it (its branch offset and ovality; the clamping error and
thermal drift are not known before welding), from ``look_ahead_mm + approach_mm`` before each
segment (the approach, arc off) to its end, with the segment's work, travel and roll angles,
the part turned by the positioner (:class:`SegmentGeometry`: the design part as placed and
turned for a segment, the nominal part of the simulator's :class:`~torchseam.sim.scene.Scene`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import overload

import numpy as np
import torch

from torchseam.core.config import CellConfig, PartConfig, Pose
from torchseam.core.part import SegmentGeometry, make_joint, nominal_part, seam_interp, torch_frames
from torchseam.core.transforms import matrix_to_quat, rotation_about
from torchseam.plan.path import SEGMENT_NAMES, SEGMENTS, PlanConfig, Segment
from torchseam.robot.kinematics import IRB1410, arm_forward, checked_values
from torchseam.robot.reach import ReachGate, ReachResult, Reason

__all__ = ["Placement", "SegmentPlan", "SegmentGeometry", "WeldPlan", "SegmentVerdict",
           "PlanEvaluator", "plan_weld", "torch_angles"]

#: :attr:`SegmentVerdict.margin_axis` when the nearest limit is the singularity margin
SINGULARITY_AXIS = 7

_Z = np.array([0.0, 0.0, 1.0])
_Y = np.array([0.0, 1.0, 0.0])


def torch_angles(work_deg: float, travel_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """(3, 3) rotation applied in the torch frame: the work angle about its x (travel
    direction), the travel angle about its y, then the roll about its (tilted) z axis. The
    first two are :func:`torchseam.geometry.torch_frame.tilt`'s, as the live loop applies them:
    a torch frame R becomes ``R @ torch_angles(work, travel, roll)``."""
    x, y = np.array([1.0, 0.0, 0.0]), _Y
    return (rotation_about(x, np.radians(work_deg)) @ rotation_about(y, np.radians(travel_deg))
            @ rotation_about(_Z, np.radians(roll_deg)))


@dataclass(frozen=True)
class Placement:
    """How the part sits, relative to its file's ``placement``: turned by ``yaw_deg`` about the
    base's vertical and tilted by ``tilt_deg`` about the base's y axis, both through the seam's
    centre (so the seam stays where it was), then shifted by ``shift_mm`` (base frame)."""

    yaw_deg: float = 0.0
    tilt_deg: float = 0.0
    shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def configured(self) -> bool:
        return self.yaw_deg == 0.0 and self.tilt_deg == 0.0 and not any(self.shift_mm)

    def matrix(self, part: PartConfig) -> np.ndarray:
        """(4, 4) pose of the joint frame {T} in the base frame {B}, mm."""
        P0 = part.placement.matrix()
        if self.configured:
            return P0
        pivot_T = _seam_centre(part)
        pivot_B = P0[:3, :3] @ pivot_T + P0[:3, 3]
        R = (rotation_about(_Z, np.radians(self.yaw_deg))
             @ rotation_about(_Y, np.radians(self.tilt_deg)) @ P0[:3, :3])
        P = np.eye(4)
        P[:3, :3] = R
        P[:3, 3] = pivot_B + np.asarray(self.shift_mm, float) - R @ pivot_T
        return P

    def placed(self, part: PartConfig) -> PartConfig:
        """``part`` with its ``placement`` moved here (the part itself when unchanged)."""
        if self.configured:
            return part
        P = self.matrix(part)
        q = matrix_to_quat(P[:3, :3])
        return dataclasses.replace(part, placement=Pose(
            tuple(float(v) for v in P[:3, 3]), tuple(float(v) for v in q / np.linalg.norm(q))))

    def describe(self) -> str:
        if self.configured:
            return "as configured"
        s = self.shift_mm
        return (f"yaw {self.yaw_deg:+g} deg, tilt {self.tilt_deg:+g} deg, shift "
                f"({s[0]:+g}, {s[1]:+g}, {s[2]:+g}) mm")


def _seam_centre(part: PartConfig) -> np.ndarray:
    """Centre of the design seam in {T} (on the branch axis, at the seam's mean height)."""
    return make_joint(nominal_part(part)).seam(np.linspace(0, 2 * np.pi, 72, endpoint=False)
                                               ).point.mean(axis=0)


@dataclass(frozen=True)
class SegmentPlan(Segment):
    """A segment (branch angles, positioner turn) with the torch's angles for it (degrees)."""

    work_angle_deg: float = 0.0
    travel_angle_deg: float = 0.0
    roll_deg: float = 0.0

    @property
    def angles(self) -> tuple[float, float, float]:
        return (self.work_angle_deg, self.travel_angle_deg, self.roll_deg)


@dataclass(frozen=True)
class WeldPlan:
    """The whole plan of one part.

    Attributes:
        part: the part with the planned placement (``part.placement``); hand it to the scene,
            the simulator and the gate instead of the file's part.
        placement: the placement relative to the part file's.
        segment_start_deg: branch angle where segment a starts.
        segments: the six segments a..f in welding order.
        searched: the configured plan failed the gate and this one was searched for.
        candidates: layouts and angle sets the search screened.
    """

    part: PartConfig
    placement: Placement
    segment_start_deg: float
    segments: tuple[SegmentPlan, ...]
    searched: bool = False
    candidates: int = 0
    search_s: float = 0.0

    def geometry(self, seg: Segment) -> SegmentGeometry:
        """The design part as placed, turned by the positioner for ``seg``."""
        return SegmentGeometry(self.part, seg.rotation_deg)

    def plan_config(self, seg: SegmentPlan, base: PlanConfig) -> PlanConfig:
        """``base`` (the planning settings) with this plan's start and ``seg``'s work and
        travel angles: the settings of the live loop for that segment. (The roll is not a
        plan setting: see :meth:`torch_rotation`.)"""
        return dataclasses.replace(base, segment_start_deg=self.segment_start_deg,
                                   work_angle_deg=seg.work_angle_deg,
                                   travel_angle_deg=seg.travel_angle_deg)

    def torch_rotation(self, seg: SegmentPlan) -> np.ndarray:
        """(3, 3) rotation in the torch frame for ``seg``'s work, travel and roll angles."""
        return torch_angles(*seg.angles)

    def nominal_tcp(self, seg: SegmentPlan, s_mm: np.ndarray) -> np.ndarray:
        """Programmed (design) torch poses of ``seg`` at seam arc lengths ``s_mm`` (N,) of
        :meth:`geometry`, with the segment's angles: (N, 4, 4) in the base frame, mm. The demo's
        start pose and programmed path."""
        T = self.geometry(seg).nominal_tcp(np.asarray(s_mm, float))
        T[:, :3, :3] = T[:, :3, :3] @ self.torch_rotation(seg)
        return T

    def search_arms(self, seg: SegmentPlan, s_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """The directions across the seam along the part's two surfaces at seam arc length
        ``s_mm`` of ``seg`` (the design part as placed and turned for it), in the base frame:
        ``(plus, minus)``, the surface on the torch's +y side and the one on its -y side, each
        perpendicular to the seam and pointing away from it (along the main body away from
        the branch, up the branch away from the main body). A torch moved across the seam
        along them keeps its height over the surface it passes over (a move along the torch's
        own y runs into one of them where the groove is 90 degrees: the plate)."""
        geo = self.geometry(seg)
        smp = geo.nominal_joint.seam(geo.phi_at(np.array([float(s_mm)])))
        x, n_m, n_b = smp.tangent[0], smp.normal_main[0], smp.normal_branch[0]
        arms = []
        for n, other in ((n_m, n_b), (n_b, n_m)):
            a = np.cross(x, n)
            a = a / np.linalg.norm(a)
            arms.append(a if a @ other > 0 else -a)   # away from the other surface
        R = geo.T_B_Tnom[:3, :3]
        main, branch = R @ arms[0], R @ arms[1]
        y = self.nominal_tcp(seg, np.array([float(s_mm)]))[0, :3, 1]
        return (main, branch) if main @ y > branch @ y else (branch, main)

    def to_dict(self) -> dict:
        p = self.part.placement
        return {
            "placement": {"relative": dataclasses.asdict(self.placement),
                          "describe": self.placement.describe(),
                          "position_mm": list(p.position_mm), "quaternion": list(p.quaternion)},
            "segment_start_deg": self.segment_start_deg,
            "segments": [{"name": s.name, "phi_start_deg": float(np.degrees(s.phi_start)),
                          "phi_end_deg": float(np.degrees(s.phi_end)),
                          "rotation_deg": s.rotation_deg, "work_angle_deg": s.work_angle_deg,
                          "travel_angle_deg": s.travel_angle_deg, "roll_deg": s.roll_deg}
                         for s in self.segments],
            "searched": self.searched, "candidates": self.candidates,
            "search_s": round(self.search_s, 3),
        }


def make_segments(start_deg: float, angles: list[tuple[float, float, float]],
                  closed: bool = True) -> tuple[SegmentPlan, ...]:
    """The six segments from ``start_deg`` (as :func:`~torchseam.plan.path.six_segments`; an
    open seam's, ``closed`` False, are not turned)."""
    step = 2 * np.pi / SEGMENTS
    phi0 = float(np.radians(start_deg))
    turn = -60.0 if closed else 0.0
    return tuple(SegmentPlan(SEGMENT_NAMES[k], k, phi0 + k * step, phi0 + (k + 1) * step,
                             turn * k, *angles[k]) for k in range(SEGMENTS))


# --------------------------------------------------------------------------- evaluation

@dataclass(frozen=True)
class SegmentVerdict:
    """The gate's verdict on one segment's poses.

    Attributes:
        poses / ok: poses checked / passed.
        other: refused for other reasons than clearance alone (reach, axis ranges,
            singularity, joint speed).
        margin_deg: the worst axis's distance to its range over the poses whose joints count
            (passed, or refused for clearance only), or to the singularity margin (the gate's
            ``min_sigma``) in degrees of axis 5 at the wrist singularity if that is nearer;
            ``-inf`` when there are none.
        margin_axis: which axis (1..6; :data:`SINGULARITY_AXIS`: the singularity; 0 when
            none).
        clearance_mm: the smallest torch-to-pipe clearance.
        first_refused: index of the first refused pose (-1: none) and its reason.
        phi_deg: (poses,) branch angle of each pose, degrees, in [0, 360) (an open seam's
            parameter in degrees, not wrapped: < 0 on the run-on tab).
        result: the gate's full result.
    """

    poses: int
    ok: int
    other: int
    margin_deg: float
    margin_axis: int
    clearance_mm: float
    first_refused: int
    reason: str
    counts: dict[str, int]
    phi_deg: np.ndarray = field(repr=False)
    result: ReachResult = field(repr=False)

    @property
    def passed(self) -> bool:
        return self.ok == self.poses


class PlanEvaluator:
    """Runs plans (or parts of them) through the reachability gate.

    Args:
        cell: tool, weld speed, step and look-ahead (``configs/cell.yaml``).
        part: the part as its file describes it.
        config: planning settings (``configs/plan.yaml``:
            :func:`~torchseam.plan.path.load_plan_config`).
        robot: the kinematic model; its config holds the gate's limits
            (``configs/robot.yaml``: :func:`~torchseam.robot.kinematics.load_irb1410`).
    """

    def __init__(self, cell: CellConfig, part: PartConfig, config: PlanConfig,
                 robot: IRB1410) -> None:
        self.cell, self.part = cell, part
        self.config = config
        self.robot = robot
        ax = self.robot.config.axes
        self._lo, self._hi = np.asarray(ax.min_deg, float), np.asarray(ax.max_deg, float)
        self._min_sigma = float(self.robot.config.singularity.min_sigma)
        self._sigma_per_deg = _sigma_per_wrist_deg(self.robot)
        self.joint = make_joint(part)
        self._phi_tab, self._s_tab = self.joint.arc_length_table()
        self._length = float(self._s_tab[-1])
        self._axis = make_joint(nominal_part(part)).d     # the positioner's axis, in {T}
        self._frames: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._placements: dict[Placement, tuple[PartConfig, np.ndarray]] = {}
        self.evaluations = 0

    def part_pose(self, placement: Placement, seg: Segment) -> np.ndarray:
        """(4, 4) pose of {T} in the base for ``seg`` (the positioner's turn applied)."""
        P = self._placed(placement)[1]
        R = np.eye(4)
        R[:3, :3] = rotation_about(self._axis, np.radians(seg.rotation_deg))
        return P @ R

    def _placed(self, placement: Placement) -> tuple[PartConfig, np.ndarray]:
        if placement not in self._placements:
            part = placement.placed(self.part)
            self._placements[placement] = (part, part.placement.matrix())
        return self._placements[placement]

    def frames(self, seg: Segment, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Torch frames along ``seg`` in {T} without the segment's angles, (N, 4, 4), and their
        branch angles (N,) rad: from the approach's start to the segment's end."""
        key = (round(seg.phi_start, 9), round(seg.phi_end, 9), stride)
        if key not in self._frames:
            proc = self.cell.process
            closed = self.joint.closed
            s_of = lambda phi: float(seam_interp(closed, phi, self._phi_tab,  # noqa: E731
                                                 self._s_tab))
            s0 = s_of(seg.phi_start)
            seg_len = (s_of(seg.phi_end) - s0) % self._length
            if seg_len < 1e-6:
                seg_len = self._length / SEGMENTS
            approach = proc.look_ahead_mm + self.config.approach_mm
            s = s0 - approach + np.arange(0.0, approach + seg_len + 1e-9, proc.step_mm)
            if stride > 1:  # keep the first and the last pose
                idx = np.unique(np.r_[np.arange(0, len(s), stride), len(s) - 1])
                s = s[idx]
            phi = seam_interp(closed, s, self._s_tab, self._phi_tab)
            self._frames[key] = (torch_frames(self.joint.seam(phi)), phi)
        return self._frames[key]

    def poses(self, placement: Placement, seg: SegmentPlan, stride: int = 1) -> np.ndarray:
        """(N, 4, 4) torch TCP poses of ``seg`` in the base frame, mm."""
        F, _ = self.frames(seg, stride)
        T = self.part_pose(placement, seg) @ F
        if any(seg.angles):
            T[:, :3, :3] = T[:, :3, :3] @ torch_angles(*seg.angles)
        return T

    def check(self, placement: Placement, seg: SegmentPlan, stride: int = 1) -> SegmentVerdict:
        """The gate's verdict on ``seg``'s poses, the part placed by ``placement``: the gate the
        live loop builds (this part, at this placement, turned for the segment), the path
        starting from the robot's home joints."""
        self.evaluations += 1
        part, _ = self._placed(placement)
        gate = ReachGate(self.robot, cell=self.cell, part=part,
                         part_pose_mm=self.part_pose(placement, seg))
        T = self.poses(placement, seg, stride)
        r = gate.check(torch.as_tensor(T, dtype=self.robot.dtype))
        _, phi = self.frames(seg, stride)
        return self._verdict(r, phi)

    def _verdict(self, r: ReachResult, phi: np.ndarray) -> SegmentVerdict:
        code = r.code
        ok = np.array([c is Reason.OK for c in code])
        counted = np.array([c in (Reason.OK, Reason.CLEARANCE) for c in code])
        q = r.q_deg.detach().cpu().numpy().astype(float)
        v = checked_values(q, self.robot.axis3_difference)
        m = np.minimum(v - self._lo, self._hi - v)                              # (N, 6)
        # the singularity margin as a seventh axis: degrees of axis 5 at the wrist singularity
        sigma = r.sigma_min.detach().cpu().numpy().astype(float)
        m = np.concatenate([m, ((sigma - self._min_sigma) / self._sigma_per_deg)[:, None]],
                           axis=1)                                              # (N, 7)
        if counted.any():
            mc = m[counted]
            i, k = np.unravel_index(int(np.argmin(mc)), mc.shape)
            margin, axis = float(mc[i, k]), int(k) + 1
        else:
            margin, axis = float("-inf"), 0
        counts: dict[str, int] = {}
        for c in code:
            if c is not Reason.OK:
                counts[c.value] = counts.get(c.value, 0) + 1
        bad = np.flatnonzero(~ok)
        first = int(bad[0]) if len(bad) else -1
        return SegmentVerdict(len(code), int(ok.sum()), int((~counted).sum()), margin, axis,
                              float(r.clearance_mm.min()), first,
                              r.reasons[first] if first >= 0 else "", counts,
                              np.degrees(np.mod(phi, 2 * np.pi) if self.joint.closed else phi), r)

    def check_plan(self, plan: WeldPlan, stride: int = 1) -> list[SegmentVerdict]:
        return [self.check(plan.placement, seg, stride) for seg in plan.segments]


# --------------------------------------------------------------------------- search

@dataclass
class _Layout:
    placement: Placement
    start_deg: float
    key: tuple
    verdicts: list[SegmentVerdict]
    verified: bool = False   # checked on every pose (else screened)


def _sigma_per_wrist_deg(robot: IRB1410) -> float:
    """How fast the gate's singularity measure (the smallest singular value of the scaled
    flange Jacobian) grows per degree of axis 5 away from the wrist singularity, at the home
    joints: what turns a pose's ``sigma_min - min_sigma`` into degrees for the plan's margin."""
    q = np.tile(np.asarray(robot.config.home_deg, float), (2, 1))
    q[:, 4] = (0.0, 1.0)
    J = arm_forward(np, robot.geometry, q)[1]
    scale = np.ones((6, 1))
    scale[:3] = 1.0 / robot.config.singularity.length_mm
    s = np.linalg.svd(J * scale, compute_uv=False)[:, -1]
    return float(max(s[1] - s[0], 1e-6))


def _grid(lo: float, hi: float, step: float) -> list[float]:
    """0 first, then outwards: 0, +step, -step, +2 step, ... within [lo, hi]."""
    out = [0.0]
    k = 1
    while k * step <= max(hi, -lo) + 1e-9:
        for v in (k * step, -k * step):
            if lo - 1e-9 <= v <= hi + 1e-9:
                out.append(float(v))
        k += 1
    return out


def _grid_within(bounds: tuple[float, ...], step: float) -> list[float]:
    """:func:`_grid` over a configured ``(lo, hi)`` range."""
    lo, hi = bounds
    return _grid(lo, hi, step)


def _moved(placement: Placement, name: str, value: float) -> Placement:
    """``placement`` with one parameter set: ``yaw_deg``, ``tilt_deg`` or ``shift_x`` /
    ``shift_y`` / ``shift_z`` (one coordinate of ``shift_mm``)."""
    if name.startswith("shift"):
        sh = list(placement.shift_mm)
        sh["xyz".index(name[-1])] = value
        return dataclasses.replace(placement, shift_mm=(sh[0], sh[1], sh[2]))
    if name == "yaw_deg":
        return dataclasses.replace(placement, yaw_deg=value)
    if name == "tilt_deg":
        return dataclasses.replace(placement, tilt_deg=value)
    raise ValueError(f"no placement parameter {name!r}")


def _circular(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


class _Search:
    def __init__(self, ev: PlanEvaluator) -> None:
        self.ev = ev
        self.cfg = ev.config
        self.s = ev.config.search
        self.stride = self.s.screen_stride
        self.angles0 = (ev.config.work_angle_deg, ev.config.travel_angle_deg, 0.0)

    # ---- layout (placement and segment start)
    def _change(self, placement: Placement, start_deg: float) -> float:
        s = self.s
        return (_circular(start_deg, configured_start(self.ev.part, self.cfg))
                / s.segment_start_step_deg
                + abs(placement.yaw_deg) / s.yaw_step_deg
                + abs(placement.tilt_deg) / s.tilt_step_deg
                + sum(abs(v) for v in placement.shift_mm) / s.shift_step_mm)

    @overload
    def layout(self, placement: Placement, start_deg: float, bound: None = None,
               stride: int | None = None) -> _Layout: ...

    @overload
    def layout(self, placement: Placement, start_deg: float, bound: tuple | None,
               stride: int | None = None) -> _Layout | None: ...

    def layout(self, placement: Placement, start_deg: float, bound: tuple | None = None,
               stride: int | None = None) -> _Layout | None:
        """Check one layout on every ``stride``-th pose (default: screen); None when it is
        already worse than ``bound`` (the best key so far) on the refused fraction."""
        stride = self.stride if stride is None else stride
        segs = make_segments(start_deg, [self.angles0] * SEGMENTS, self.ev.joint.closed)
        total = sum(len(self.ev.frames(seg, stride)[1]) for seg in segs)
        verdicts = []
        other = 0
        for seg in segs:
            v = self.ev.check(placement, seg, stride)
            verdicts.append(v)
            other += v.other
            if bound is not None and other / total > bound[0]:
                return None
        margin = min(v.margin_deg for v in verdicts)
        short = max(0.0, self.s.min_joint_margin_deg - margin)
        # the refused fraction: screened and fully checked layouts compare
        key = (round(other / total, 9), round(short, 6),
               round(self._change(placement, start_deg), 6), -margin)
        return _Layout(placement, start_deg, key, verdicts, stride == 1)

    def starts(self, around: float | None = None, window: int | None = None) -> list[float]:
        if not self.ev.joint.closed:
            return [0.0]   # an open seam starts at its start
        step = self.s.segment_start_step_deg
        n = int(round(360.0 / step))
        base = self.cfg.segment_start_deg if around is None else around
        ks = range(n) if window is None else [k % n for k in range(-window, window + 1)]
        return sorted({float((base + k * step) % 360.0) for k in ks},
                      key=lambda a: _circular(a, base))

    def search_layout(self) -> _Layout:
        """The best layout (placement and segment start), checked on every pose."""
        lays = _Layouts(self)
        for start in self.starts():
            lays.consider(Placement(), start)
        top = lays.settle()
        if self._good(top):
            return top
        self._descend(lays)
        placement = lays.best().placement
        if placement != Placement():  # (the configured one had every start already)
            for start in self.starts():
                lays.consider(placement, start)
        return lays.settle()

    def _placement_grids(self) -> dict[str, list[float]]:
        """The values of each placement parameter, in the order the descent takes them."""
        s = self.s
        tilts = _grid_within(s.tilt_deg, s.tilt_step_deg)
        upright = self.ev.part.intersection_angle_deg - 90.0  # stands the branch upright
        if upright != 0.0 and s.tilt_deg[0] - 1e-9 <= upright <= s.tilt_deg[1] + 1e-9:
            tilts.insert(1, float(upright))
        shifts = _grid_within(s.shift_mm, s.shift_step_mm)
        return {"tilt_deg": tilts, "yaw_deg": _grid_within(s.yaw_deg, s.yaw_step_deg),
                "shift_x": shifts, "shift_y": shifts, "shift_z": shifts}

    def _descend(self, lays: _Layouts) -> None:
        """Coordinate descent on the placement (up to three sweeps), the start re-chosen near
        the best one, until a layout is good or a sweep improves nothing."""
        grids = self._placement_grids()
        for _ in range(3):
            improved = False
            for name, values in grids.items():
                improved |= self._sweep(lays, name, values)
                if self._good(lays.best()):
                    break
            if self._good(lays.best()) or not improved:
                break

    def _sweep(self, lays: _Layouts, name: str, values: list[float]) -> bool:
        """Try every value of one placement parameter on the best layout; whether one of them
        improved it."""
        improved = False
        for v in values:
            top = lays.best()
            cand = _moved(top.placement, name, v)
            if cand == top.placement:
                continue
            for start in self.starts(top.start_deg, window=1):
                improved |= lays.consider(cand, start)
        return improved

    def _good(self, lay: _Layout) -> bool:
        return lay.key[0] == 0 and lay.key[1] == 0.0

    # ---- per segment angles
    def angles(self, placement: Placement, seg: SegmentPlan) -> tuple[SegmentPlan, int]:
        """The segment with angles that pass the gate (screened), or the segment itself when
        none do; and the candidates tried. Work angles first (travel as configured), then
        travel angles with the best work angle, then the grid around the best pair, then the
        roll."""
        s = self.s
        w0, t0, _ = self.angles0
        tried = 0
        cache: dict[tuple[float, float, float], tuple] = {}

        def score(a: tuple[float, float, float]) -> tuple:
            nonlocal tried
            if a not in cache:
                cand = dataclasses.replace(seg, work_angle_deg=a[0], travel_angle_deg=a[1],
                                           roll_deg=a[2])
                v = self.ev.check(placement, cand, self.stride)
                tried += 1
                short = max(0.0, s.min_joint_margin_deg - v.margin_deg)
                cost = (abs(a[0] - w0) + abs(a[1] - t0) + abs(a[2])) / s.angle_step_deg
                cache[a] = (v.poses - v.ok, round(short, 6), round(cost, 6), -v.margin_deg,
                            -v.clearance_mm)
            return cache[a]

        step = s.angle_step_deg
        works = [w0 + d for d in _grid(s.work_angle_deg[0] - w0, s.work_angle_deg[1] - w0, step)]
        travels = [t0 + d for d in _grid(s.travel_angle_deg[0] - t0,
                                         s.travel_angle_deg[1] - t0, step)]
        best = min(((w, t0, 0.0) for w in works), key=score)
        best = min(((best[0], t, 0.0) for t in travels), key=score)
        near = [(w, t, 0.0) for w in works for t in travels
                if abs(w - best[0]) <= step + 1e-9 and abs(t - best[1]) <= step + 1e-9]
        best = min(near, key=score)
        if score(best)[0] > 0:
            best = min([best] + [(best[0], best[1], r)
                                 for r in _grid_within(s.roll_deg, s.roll_step_deg)[1:]], key=score)
        if score(best)[0] > 0:
            return seg, tried  # no angles pass it: keep the configured ones (and say why)
        return dataclasses.replace(seg, work_angle_deg=best[0], travel_angle_deg=best[1],
                                   roll_deg=best[2]), tried


class _Layouts:
    """The layouts a search has checked, by (placement, start)."""

    def __init__(self, search: _Search) -> None:
        self.search = search
        self.seen: dict[tuple[Placement, float], _Layout] = {}

    def best(self) -> _Layout:
        return min(self.seen.values(), key=lambda lay: lay.key)

    def consider(self, placement: Placement, start: float) -> bool:
        """Screen a layout (unless seen); whether it is the best so far."""
        if (placement, start) in self.seen:
            return False
        bound = self.best().key if self.seen else None
        lay = self.search.layout(placement, start, bound)
        if lay is None:
            return False
        self.seen[(placement, start)] = lay
        return bound is None or lay.key < bound

    def settle(self, budget: int = 6) -> _Layout:
        """Check the best screened layouts on every pose until the best is checked (a
        screen misses a lone refused pose: a joint-speed spike, a singular pose)."""
        for _ in range(budget):
            top = self.best()
            if top.verified:
                return top
            full = self.search.layout(top.placement, top.start_deg, stride=1)
            self.seen[(top.placement, top.start_deg)] = full
        done = [lay for lay in self.seen.values() if lay.verified]
        return min(done, key=lambda lay: lay.key) if done else self.best()


def configured_start(part: PartConfig, cfg: PlanConfig) -> float:
    """Where segment a starts as configured (degrees of the seam parameter): ``cfg``'s
    ``segment_start_deg`` round a ring; an open seam's start (0)."""
    return cfg.segment_start_deg if make_joint(part).closed else 0.0


def configured_plan(part: PartConfig, cfg: PlanConfig) -> WeldPlan:
    """The plan as configured: the part file's placement, ``segment_start_deg`` (an open seam:
    its start) and the work and travel angles of ``cfg`` (the planning settings), no roll."""
    angles = (cfg.work_angle_deg, cfg.travel_angle_deg, 0.0)
    start = configured_start(part, cfg)
    return WeldPlan(part, Placement(), start,
                    make_segments(start, [angles] * SEGMENTS, make_joint(part).closed))


def plan_weld(ev: PlanEvaluator, *, configured: list[SegmentVerdict] | None = None
              ) -> WeldPlan:
    """The weld plan of the evaluator's part (``ev`` holds the cell, the part, the planning
    settings and the robot): the configured one when the gate passes all its poses, else the
    one the search finds (module docstring). The returned plan may still fail the gate (a part
    out of the robot's reach, a joint the torch does not fit): check it with
    :func:`torchseam.plan.preflight.preflight`.

    ``configured``: the configured plan's verdicts when the caller has them already.
    """
    part = ev.part
    plan = configured_plan(part, ev.config)
    if configured is None:
        configured = ev.check_plan(plan)
    if all(v.passed for v in configured):
        return plan
    t0 = time.perf_counter()
    n0 = ev.evaluations
    search = _Search(ev)
    lay = search.search_layout()
    segs = list(make_segments(lay.start_deg, [search.angles0] * SEGMENTS, ev.joint.closed))
    full = lay.verdicts if lay.verified else [ev.check(lay.placement, seg) for seg in segs]
    for k, v in enumerate(full):
        # (nothing the torch's angles could turn: no pose of it within the arm's reach)
        if not v.passed and v.counts.get(Reason.UNREACHABLE.value, 0) < v.poses:
            segs[k], _ = search.angles(lay.placement, segs[k])
    return WeldPlan(lay.placement.placed(part), lay.placement, lay.start_deg, tuple(segs),
                    searched=True, candidates=ev.evaluations - n0,
                    search_s=time.perf_counter() - t0)
