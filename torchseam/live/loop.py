"""The live loop: frame -> feature point -> 3D -> torch frame -> IPI plan -> gate -> EGM.

One :class:`LiveLoop` per camera. Call :meth:`LiveLoop.start` on a clean (arc-off) frame, then
:meth:`LiveLoop.on_frame` for every frame (``None`` for a frame that did not arrive). It locates
the seam, keeps the located points in the bounded look-ahead buffer, and whenever the torch
has closed in on its current target it plans the next IPI step (2 mm), builds the torch frame
from ECAL's arms, and hands the pose to the EGM link, which runs the reachability gate and its
own safety checks before anything reaches the robot.

It never moves blind: targets are only taken from located points, and points the tracker only
coasted through (filter prediction, no trusted measurement) are used for at most
``max_blind_mm`` of travel past the last trusted point; beyond that the loop holds (sends no
new target; the link's watchdog then holds the robot) and says why, and it resumes when
trusted measurements return.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import Enum
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, overload

import numpy as np
from scipy.spatial import cKDTree

from torchseam.core.config import CONFIG_DIR, CellConfig, load_config
from torchseam.core.transforms import matrix_to_quat, quat_to_matrix
from torchseam.geometry.torch_frame import MIN_ARM_MM, MIN_SIN
from torchseam.live.locate import Location, SeamLocator
from torchseam.plan.path import LookAheadBuffer, PlanConfig, load_plan_config
from torchseam.robot.egm import Verdict
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import FrameTracker

if TYPE_CHECKING:  # torchseam.live.demo imports this module
    from torchseam.live.demo import DemoControl, DemoEvent


@dataclass(frozen=True)
class LiveConfig:
    """Live-loop settings (``configs/live.yaml``)."""

    lead_mm: float             # send the next target when the torch is this close to the last
    max_blind_mm: float        # travel allowed past the last trusted measurement
    max_turn_deg: float        # largest torch rotation between two targets
    max_offset_mm: float       # largest distance of a target from the programmed path
    max_frame_gap_ms: float    # no camera frame for longer than this: hold
    timing_window: int         # per-stage timings kept (bounded)
    history: int               # commands kept in LiveLoop.commands (bounded; oldest dropped)

    def _check(self) -> None:
        if self.timing_window < 1 or self.history < 1:
            raise ValueError("timing_window and history must be >= 1")


_T = TypeVar("_T")


class History(deque[_T]):
    """A bounded history (a ``deque`` with ``maxlen``) that also takes slices, as a list does:
    ``history[k:]`` is a list of the entries from position ``k`` on."""

    def __init__(self, items: Iterable[_T] = (), maxlen: int | None = None) -> None:
        super().__init__(items, maxlen)

    @overload
    def __getitem__(self, i: int) -> _T: ...
    @overload
    def __getitem__(self, i: slice) -> list[_T]: ...
    def __getitem__(self, i: int | slice) -> _T | list[_T]:  # noqa: E301
        if isinstance(i, slice):
            start, stop, step = i.indices(len(self))
            if step == 1:
                return list(islice(self, start, max(start, stop)))
            return list(self)[i]
        return super().__getitem__(i)


def _turn_limited(q_prev: np.ndarray | None, q: np.ndarray, max_deg: float) -> np.ndarray:
    """Slerp from ``q_prev`` towards ``q`` by at most ``max_deg`` (quaternions (4,) w, x, y,
    z, same hemisphere): the torch turns to a newly seen frame over several steps."""
    if q_prev is None:
        return q
    d = min(1.0, max(-1.0, float(q_prev @ q)))
    half = math.acos(abs(d))
    ang = 2.0 * math.degrees(half)
    if ang <= max_deg:
        return q
    f = max_deg / ang
    out = (math.sin((1 - f) * half) * q_prev
           + math.copysign(1.0, d) * math.sin(f * half) * q) / math.sin(half)
    return out / np.linalg.norm(out)


def _rot(axis: int, deg: float) -> np.ndarray:
    """(3, 3) rotation by ``deg`` about coordinate axis ``axis`` (0 x, 1 y, 2 z)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    M = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    M[i, i], M[i, j], M[j, i], M[j, j] = c, -s, s, c
    return M


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ~25 us a call on 3-vectors)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def frame_from_arms(p: np.ndarray, q1: np.ndarray, q2: np.ndarray, tangent: np.ndarray
                    ) -> tuple[np.ndarray, bool]:
    """The torch frame of :func:`torchseam.geometry.torch_frame.torch_frame` with a seam
    tangent (Omega perpendicular to the seam, px along the tangent), for one point in numpy.

    The live loop plans one pose per step; the torch version pays ~1.5 ms of per-call tensor
    overhead on these 3-vectors, this one ~30 us (``tests/test_live.py`` holds the two to the
    same numbers).

    Args:
        p: (3,) weld point; q1, q2: (3,) a point on each stripe arm; tangent: (3,) the seam's
            direction of travel (need not be unit). All mm, base frame.

    Returns:
        ``(R, ok)``: (3, 3) rotation with columns (wx, wy, wz) and whether the points define a
        frame (coincident or collinear arms: ``ok`` False and the identity).
    """
    t = tangent / max(float(np.linalg.norm(tangent)), 1e-12)
    u1, u2 = q1 - p, q2 - p
    u1 = u1 - (u1 @ t) * t
    u2 = u2 - (u2 @ t) * t
    n1, n2 = float(np.linalg.norm(u1)), float(np.linalg.norm(u2))
    cross = _cross(u1, u2)
    nc = float(np.linalg.norm(cross))
    sin = nc / max(n1 * n2, 1e-12)
    if not (n1 > MIN_ARM_MM and n2 > MIN_ARM_MM and sin > MIN_SIN and math.isfinite(nc)):
        return np.eye(3), False
    px = cross / max(nc, 1e-12)                                        # eq. 27
    if px @ t < 0:
        px = -px
    pz = u1 / max(n1, 1e-12) + u2 / max(n2, 1e-12)                     # eq. 28
    pz = pz / max(float(np.linalg.norm(pz)), 1e-12)
    py = _cross(pz, px)
    return np.stack([px, -py, -pz], axis=1), True                      # eq. 29


def load_live_config(path: str | Path | None = None) -> LiveConfig:
    return load_config(LiveConfig, path or CONFIG_DIR / "live.yaml")


class LoopState(str, Enum):
    STARTING = "starting"
    TRACKING = "tracking"
    COASTING = "coasting"
    HOLD = "hold"
    DONE = "done"


class PoseSink(Protocol):
    """What the loop sends poses to (the EGM link in pose mode)."""

    def set_target(self, position_mm: Any, quaternion: Any, measured_at: float | None = None
                   ) -> Any: ...


@dataclass
class Command:
    """A pose handed to the link, and what the link said."""

    t_s: float
    p: np.ndarray          # (3,) mm, base
    q: np.ndarray          # (4,) w, x, y, z
    ok: bool
    reason: str
    seen_t_s: float        # time of the frame that located the target


@dataclass
class StepReport:
    state: LoopState
    location: Location | None
    command: Command | None
    message: str = ""


@dataclass
class LoopStats:
    frames: int = 0
    dropped_frames: int = 0
    sent: int = 0
    refused: Counter = field(default_factory=Counter)
    holds: int = 0
    timings_ms: dict[str, deque] = field(default_factory=dict)

    def add_time(self, stage: str, ms: float, maxlen: int) -> None:
        self.timings_ms.setdefault(stage, deque(maxlen=maxlen)).append(ms)


class LiveLoop:
    """Seeing, planning and commanding for one sensor (see the module docstring).

    Args:
        cell: calibration and process settings.
        tracker: the feature-point tracker (EAKF-STC by default in the demo).
        sink: where poses go (:class:`~torchseam.robot.egm.EgmLink` in pose mode).
        plan / live: settings (default ``configs/plan.yaml`` / ``configs/live.yaml``).
        nominal: (N, 3) the programmed (design) path, densely sampled (mm, base). A target
            farther than ``max_offset_mm`` from it is not sent: the tracker has left the seam
            (a box tracker sliding along the stripe, say) and the loop holds.
    """

    def __init__(self, cell: CellConfig, tracker: FrameTracker, sink: PoseSink,
                 plan: PlanConfig | None = None, live: LiveConfig | None = None,
                 nominal: np.ndarray | None = None) -> None:
        self.cell = cell
        self.plan = plan or load_plan_config()
        self.cfg = live or load_live_config()
        self.locator = SeamLocator(cell, tracker)
        self.sink = sink
        self.nominal = None if nominal is None else np.asarray(nominal, float)
        # nearest programmed point per target in ~10 us (a dense path has thousands)
        self._nominal_tree = None if nominal is None else cKDTree(self.nominal)
        self.buffer = LookAheadBuffer(self.plan.buffer_points, self.plan.smooth_mm)
        self.stats = LoopStats()
        self.state = LoopState.STARTING
        self.target: np.ndarray | None = None
        self.last_q: np.ndarray | None = None   # (4,) w, x, y, z of the last accepted pose
        self.last_trusted: np.ndarray | None = None
        self.fresh_t = float("-inf")   # time of the newest frame the tracker followed
        self.last_frame_t = float("inf")  # time of the newest frame that arrived
        # the recent commands (bounded: ``history`` in configs/live.yaml); a caller that needs
        # every command collects StepReport.command itself
        self.commands: History[Command] = History(maxlen=self.cfg.history)
        self.message = ""
        self._tilt = (_rot(0, self.plan.work_angle_deg) @ _rot(1, self.plan.travel_angle_deg))
        # prepare()'s pose: (the buffer's answer it came from, last_q then, tangent, pose)
        self._prepared: tuple[tuple, np.ndarray | None, np.ndarray,
                              tuple[np.ndarray, np.ndarray]] | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self, frame: np.ndarray, T_B_W: np.ndarray, uv0: np.ndarray | None = None
              ) -> None:
        """Start on a clean frame with the torch at ``T_B_W`` (4, 4) mm: TIPM finds the
        stripe's feature point, or ``uv0`` (2,) gives it."""
        self.locator.start(frame, uv0)
        self.last_frame_t = float("-inf")
        self.target = np.asarray(T_B_W, float)[:3, 3].copy()
        self.last_q = matrix_to_quat(np.asarray(T_B_W, float)[:3, :3])
        self._prepared = None
        self.state = LoopState.TRACKING

    def finish(self) -> None:
        self.state = LoopState.DONE

    # ------------------------------------------------------------------ per frame
    def on_frame(self, frame: np.ndarray | None, T_B_F: np.ndarray, T_B_W: np.ndarray,
                 t_s: float) -> StepReport:
        """One camera frame (``None``: it did not arrive) taken with the flange at ``T_B_F``;
        ``T_B_W`` is the torch's actual pose now, ``t_s`` the frame time (link clock)."""
        t0 = time.perf_counter()
        self.stats.frames += 1
        loc = None
        if frame is None:
            self.stats.dropped_frames += 1
            gap_ms = (t_s - self.last_frame_t) * 1e3
            if gap_ms > self.cfg.max_frame_gap_ms and self.state not in (
                    LoopState.DONE, LoopState.STARTING):
                self._hold(f"no camera frame for {self.cfg.max_frame_gap_ms:g}+ ms: holding")
                self.stats.add_time("frame->command", (time.perf_counter() - t0) * 1e3,
                                    self.cfg.timing_window)
                return StepReport(self.state, None, None, self.message)
        else:
            self.last_frame_t = t_s
            loc = self.locator.step(frame, T_B_F)
            for k, v in loc.timings_ms.items():
                self.stats.add_time(k, v, self.cfg.timing_window)
        # a point counts as located only with the stripe seen around it (ECAL's arms):
        # a coasting filter's guess over a dark or blinded frame is not a seam point
        located = loc is not None and bool(
            np.all(np.isfinite(loc.p)) and loc.status != TrackStatus.LOST and loc.arms_ok)
        if located:
            self.fresh_t = t_s
            if loc.status == TrackStatus.TRACKED:
                self.last_trusted = loc.p
        # The frame's point joins the buffer after the frame's command, which rests on the
        # plan prepare() made between frames from the points located before. The stripe is
        # ~20 mm ahead of the torch, so a new point reaches the fit at the next target only at
        # a segment's start; entered first, it made those commands re-plan and re-gate on the
        # frame (~1 % of frames, the slowest: 3-5 ms of plan). With nothing buffered yet there
        # is nothing else to plan from: it goes in first.
        late = located and len(self.buffer) > 0
        if located and not late:
            self.buffer.push(loc.p, loc.q, t_s, guessed=loc.arms_fallback)
        t1 = time.perf_counter()
        cmd = self._command(T_B_W[:3, 3], t_s, loc)
        t2 = time.perf_counter()
        if late:
            self.buffer.push(loc.p, loc.q, t_s, guessed=loc.arms_fallback)
        self.stats.add_time("plan+gate+send", (t2 - t1) * 1e3, self.cfg.timing_window)
        self.stats.add_time("frame->command", (t2 - t0) * 1e3, self.cfg.timing_window)
        self.prepare()  # the next target, while the camera exposes the next frame
        self.stats.add_time("prepare", (time.perf_counter() - t2) * 1e3, self.cfg.timing_window)
        return StepReport(self.state, loc, cmd, self.message)

    def _command(self, torch_p: np.ndarray, t_s: float, loc: Location | None) -> Command | None:
        """Plan and send. The measurement time handed to the link is that of the newest frame
        the tracker followed (not of the target's own frame, which is a look-ahead older):
        it is how fresh the tracking is, and the link refuses stale tracking."""
        if self.state in (LoopState.DONE, LoopState.STARTING) or self.target is None:
            return None
        if np.linalg.norm(torch_p - self.target) > self.cfg.lead_mm:
            # on its way to the current target: re-send it while tracking is alive, which
            # keeps the link's watchdog fed; with tracking gone it lapses and the link holds
            alive = loc is not None and loc.status != TrackStatus.LOST
            if self.last_q is not None and alive and (
                    self.state != LoopState.HOLD or loc.status == TrackStatus.TRACKED):
                verdict = self.sink.set_target(self.target, self.last_q,
                                               measured_at=self.fresh_t)
                if bool(getattr(verdict, "ok", True)):
                    self._set_state(loc)
                else:  # the link holds the robot (stale tracking, say): say so, as below
                    self._hold(f"link refused the pose ({getattr(verdict, 'reason', 'refused')})")
            return None
        pose = self._pose(self.buffer.next_command(self.target, self.cell.process.step_mm))
        if isinstance(pose, str):
            return self._hold(pose)
        ip, q = pose
        seen = self._seen_time(ip)
        verdict = self.sink.set_target(ip, q, measured_at=self.fresh_t)
        ok_v = bool(getattr(verdict, "ok", True))
        reason = getattr(verdict, "detail", "") or getattr(verdict, "reason", "")
        cmd = Command(t_s, ip, q, ok_v, reason, seen)
        self.commands.append(cmd)
        if ok_v:
            self.stats.sent += 1
            self.target = ip
            self.last_q = q
            self._set_state(loc)
        else:
            key = getattr(verdict, "reason", "refused")
            self.stats.refused[key] += 1
            self._hold(f"link refused the pose ({key})")  # the detail is in the link's log
        return cmd

    def _pose(self, nxt: tuple[np.ndarray, np.ndarray | None, np.ndarray] | None
              ) -> tuple[np.ndarray, np.ndarray] | str:
        """The next target pose ``(ip (3,), q (4,))`` from the look-ahead buffer's IPI step
        ``nxt``, or why there is none (the loop then holds with that message)."""
        if nxt is None:
            return "nothing located a step ahead of the torch"
        ip, tangent, arms = nxt
        prep = self._prepared
        if prep is not None and prep[0] is nxt and prep[1] is self.last_q:
            # prepare() made this pose from this very answer and the same previous pose: only
            # the blind-move check can differ (a trusted point may have come in since)
            tangent, pose = prep[2], prep[3]
            return self._blind(ip, tangent) or pose
        if tangent is None:
            # too little of the seam seen to fit its direction (the start of a segment): keep
            # the torch's present travel direction rather than guess from a chord
            tangent = quat_to_matrix(self.last_q)[:, 0]
        blind = self._blind(ip, tangent)
        if blind:
            return blind
        if self._nominal_tree is not None:
            off = float(self._nominal_tree.query(ip)[0])
            if off > self.cfg.max_offset_mm:
                return (f"target {off:.1f} mm off the programmed path (limit "
                        f"{self.cfg.max_offset_mm:g} mm): tracking suspect")
        if not np.all(np.isfinite(arms)):
            return "no arm points (ECAL) near the target: no torch frame"
        R, ok = frame_from_arms(ip, ip + arms[0], ip + arms[1], tangent)
        if not ok:
            return "degenerate torch frame (arms collinear)"
        q = matrix_to_quat(R @ self._tilt)
        if self.last_q is not None and q @ self.last_q < 0:
            q = -q  # the sign nearest the previous pose: the controller turns the short way
        return ip, _turn_limited(self.last_q, q, self.cfg.max_turn_deg)

    def _blind(self, ip: np.ndarray, tangent: np.ndarray) -> str:
        """Why ``ip`` may not be commanded blind ('' when it may)."""
        if self.last_trusted is None or self._beyond(ip, self.last_trusted, tangent,
                                                      self.cfg.max_blind_mm):
            return (f"no trusted measurement within {self.cfg.max_blind_mm:g} mm "
                    "ahead: refusing to move blind")
        return ""

    def prepare(self) -> None:
        """Work between frames: the tracker's learning for the next frame (its ``idle()``),
        and the plan of the target after the current one (the look-ahead
        buffer's seam fit) and let the sink's gate check its pose, so that the frame which
        finds the torch at its target only has to send. Changes no decision: the buffer drops
        the plan when a new point could change it and the gate re-checks a pose that differs
        (:meth:`LookAheadBuffer.prepare`, :meth:`ReachGate.prepare`). ``on_frame`` calls
        this after the frame's command is out; it is timed as the ``prepare`` stage."""
        idle = getattr(self.locator.tracker, "idle", None)
        if idle is not None:
            idle()  # the tracker's learning for the next frame (EAKF-STC's context model)
        if self.state in (LoopState.DONE, LoopState.STARTING) or self.target is None:
            return
        step = self.cell.process.step_mm
        self.buffer.prepare(self.target, step)
        nxt = self.buffer.next_command(self.target, step)
        self._prepared = None
        pose = self._pose(nxt)
        if isinstance(pose, str):
            return
        tangent = nxt[1] if nxt[1] is not None else quat_to_matrix(self.last_q)[:, 0]
        self._prepared = (nxt, self.last_q, tangent, pose)
        ready = getattr(self.sink, "prepare", None)
        if ready is not None:
            ready(*pose)

    @staticmethod
    def _beyond(ip: np.ndarray, ref: np.ndarray, tangent: np.ndarray, margin: float) -> bool:
        """ip lies more than ``margin`` past ref along the travel direction."""
        return float((ip - ref) @ tangent) > margin

    def _seen_time(self, ip: np.ndarray) -> float:
        """When the buffered point nearest ``ip`` was seen (one vectorised search: a norm
        per point cost ~0.3 ms a command with the ~100 points of the look-ahead)."""
        pts = self.buffer.points
        if not pts:
            return float("nan")
        P = np.array([loc.p for loc in pts])
        return pts[int(np.argmin(np.einsum("ij,ij->i", P - ip, P - ip)))].t_s

    def _hold(self, why: str) -> None:
        if self.state != LoopState.HOLD:
            self.stats.holds += 1
        self.state = LoopState.HOLD
        self.message = why
        return None

    def _set_state(self, loc: Location | None) -> None:
        if loc is None:
            return
        self.state = (LoopState.TRACKING if loc.status == TrackStatus.TRACKED
                      else LoopState.COASTING)
        self.message = ""

    def latency_ms(self) -> dict[str, tuple[float, float]]:
        """(p50, p99) per stage."""
        return {k: (float(np.percentile(v, 50)), float(np.percentile(v, 99)))
                for k, v in self.stats.timings_ms.items() if len(v)}


# --------------------------------------------------------------------------- open-loop replay

class RecordingSink:
    """A pose sink that moves nothing: it accepts every finite pose with a unit quaternion and
    keeps the last ``maxlen`` (bounded). What an open-loop replay hands its poses to."""

    def __init__(self, maxlen: int = 10_000) -> None:
        self.poses: deque[tuple[np.ndarray, np.ndarray, float | None]] = deque(maxlen=maxlen)
        self.accepted = 0
        self.refused = 0

    def set_target(self, position_mm: Any, quaternion: Any, measured_at: float | None = None
                   ) -> Verdict:
        p = np.asarray(position_mm, float).reshape(-1)
        q = np.asarray(quaternion, float).reshape(-1)
        if p.shape != (3,) or q.shape != (4,) or not (np.isfinite(p).all()
                                                      and np.isfinite(q).all()):
            self.refused += 1
            return Verdict(False, "non_finite", f"bad pose {p}, {q}")
        if abs(float(np.linalg.norm(q)) - 1.0) > 1e-6:
            self.refused += 1
            return Verdict(False, "bad_quaternion", f"quaternion norm {np.linalg.norm(q):.6f}")
        self.accepted += 1
        self.poses.append((p.copy(), q.copy(), measured_at))
        return Verdict(True)


@dataclass
class ReplayResult:
    """What an open-loop replay of recorded frames found (N frames after the start frame).

    Attributes:
        index: (N,) frame numbers; t_s: (N,) frame times; uv: (N, 2) tracked pixels;
        status: (N,) TrackStatus; label: (N, 2) labelled pixels (NaN: none);
        p: (N, 3) located seam points (base, mm; NaN when not located);
        p_true: (N, 3) true seam points from the recording's meta.json (NaN: none).
        commands: every pose handed to the sink; latency: (p50, p99) ms per loop stage;
        read_ms: (p50, p99) of reading a frame from the source (not part of the loop);
        poses_known: whether the source gave the torch pose of every frame.
    """

    index: np.ndarray
    t_s: np.ndarray
    uv: np.ndarray
    status: np.ndarray
    label: np.ndarray
    p: np.ndarray
    p_true: np.ndarray
    commands: list[Command]
    latency: dict[str, tuple[float, float]]
    read_ms: tuple[float, float]
    poses_known: bool
    start_index: int = 0
    messages: list[str] = field(default_factory=list)
    stopped: bool = False      # ended early by ``control`` (run_replay's operator stop)

    def pixel_errors(self) -> np.ndarray:
        """(M,) px distances tracked-to-label over the frames with a label and a track."""
        d = np.linalg.norm(self.uv - self.label, axis=1)
        return d[np.isfinite(d)]


def run_replay(cell: CellConfig, source: Iterable[Any], tracker: FrameTracker,
               T_B_W: np.ndarray | None = None, uv0: np.ndarray | None = None,
               live: LiveConfig | None = None, plan: PlanConfig | None = None,
               max_frames: int | None = None, sink: PoseSink | None = None,
               truth: dict[int, np.ndarray] | None = None,
               observer: Callable[[DemoEvent], None] | None = None,
               control: DemoControl | None = None) -> ReplayResult:
    """Feed recorded frames through a :class:`LiveLoop` (open loop: nothing moves).

    Each frame's flange pose is the recorded torch pose (``Frame.T_B_W``, from a recording's
    ``meta.json``) times the inverse tool; frames without one use ``T_B_W`` (default: the
    flange at the base origin, so 3D points come out in the flange frame). The loop's torch is
    an ideal follower: it sits on its last target once the recorded torch has come level with
    it along the travel direction (without recorded poses: always), so the loop plans one IPI
    step per step of recorded travel, as in the cell.

    Args:
        cell: calibration and process settings.
        source: iterable of :class:`~torchseam.live.sources.Frame` (any frame source).
        tracker: the feature-point tracker.
        T_B_W: (4, 4) torch pose for frames that carry none.
        uv0: (2,) start pixel (default: TIPM on the first frame, which must be arc-off).
        max_frames: stop after this many frames.
        sink: where poses go (default a :class:`RecordingSink`).
        truth: frame number -> (3,) true seam point (base, mm), for the 3D error.
        observer: called once per frame (the start frame included, with ``report`` None)
            with a :class:`~torchseam.live.demo.DemoEvent`, as in ``run_demo``: segment
            ``"replay"``, the frame's label as ``uv_true`` and ``truth`` as ``p_true`` (NaN
            where unknown), ``torch_err_mm`` NaN (nothing moves), ``link`` the sink.
        control: a :class:`~torchseam.live.demo.DemoControl`; ``checkpoint()`` runs before
            each frame is read (hold: wait; stop: end here, ``stopped`` True).

    Raises:
        TorchseamError: the start frame shows no usable stripe (names the frame).
    """
    from torchseam.core.errors import TorchseamError
    from torchseam.core.transforms import invert

    cfg = live or load_live_config()
    loop = LiveLoop(cell, tracker, sink or RecordingSink(), plan, cfg)
    tool_inv = invert(cell.tool.matrix())
    fixed = (np.asarray(T_B_W, float) if T_B_W is not None else cell.tool.matrix())
    rows: list[tuple] = []
    commands: list[Command] = []
    read: list[float] = []
    messages: list[str] = []
    poses_known, started, start_index, last_msg = True, False, 0, ""
    stopped = False
    sink = loop.sink
    if observer is not None:
        from torchseam.live.demo import DemoEvent, FrameRecord  # demo imports this module
    nan2, nan3 = np.full(2, np.nan), np.full(3, np.nan)
    it = iter(source)
    n = 0
    while max_frames is None or n < max_frames:
        if control is not None and control.checkpoint():
            stopped = True
            messages.append(f"[frame {n}] stopped by the operator")
            break
        t0 = time.perf_counter()
        try:
            fr = next(it)
        except StopIteration:
            break
        read.append((time.perf_counter() - t0) * 1e3)
        n += 1
        rec = fr.T_B_W if fr.T_B_W is not None else fixed
        poses_known &= fr.T_B_W is not None
        if not started:
            try:
                loop.start(fr.image, rec, uv0)
            except TorchseamError as e:
                raise TorchseamError(f"frame {fr.index}: {e}") from None
            started, start_index = True, fr.index
            if observer is not None:
                rec0 = FrameRecord("replay", fr.t_s, False, nan2,
                                   fr.label if fr.label is not None else nan2,
                                   int(TrackStatus.LOST), LoopState.STARTING.value, nan3,
                                   truth.get(fr.index, nan3) if truth else nan3, math.nan, "")
                observer(DemoEvent("replay", n - 1, fr.image, rec0, None, np.array(rec, float),
                                   loop, sink))
            continue
        torch_T = np.array(rec, float)
        if loop.target is not None and loop.last_q is not None:
            x = quat_to_matrix(loop.last_q)[:, 0]
            if fr.T_B_W is None or float((rec[:3, 3] - loop.target) @ x) >= 0.0:
                torch_T[:3, 3] = loop.target
        rep = loop.on_frame(fr.image, rec @ tool_inv, torch_T, fr.t_s)
        if rep.command is not None:
            commands.append(rep.command)
        if rep.message and rep.message != last_msg:
            messages.append(f"[frame {fr.index} t={fr.t_s:.2f}s] {rep.state.value}: "
                            f"{rep.message}")
        last_msg = rep.message
        loc = rep.location
        rows.append((fr.index, fr.t_s, loc.uv if loc else nan2,
                     int(loc.status) if loc else int(TrackStatus.LOST),
                     fr.label if fr.label is not None else nan2,
                     loc.p if loc else nan3,
                     truth.get(fr.index, nan3) if truth else nan3))
        if observer is not None:
            r = rows[-1]
            observer(DemoEvent("replay", n - 1, fr.image, FrameRecord(
                "replay", fr.t_s, True, r[2], r[4], r[3], rep.state.value, r[5], r[6],
                math.nan, ""), rep, torch_T, loop, sink))
    if not started and not stopped:
        raise TorchseamError("the source gave no frames")
    close = getattr(source, "close", None)
    if close is not None:
        close()

    def col(i: int, shape: tuple[int, ...]) -> np.ndarray:
        return (np.array([r[i] for r in rows], float) if rows
                else np.zeros((0, *shape)))

    return ReplayResult(
        col(0, ()).astype(int), col(1, ()), col(2, (2,)), col(3, ()).astype(int),
        col(4, (2,)), col(5, (3,)), col(6, (3,)), commands, loop.latency_ms(),
        (float(np.percentile(read, 50)), float(np.percentile(read, 99))) if read
        else (math.nan, math.nan), poses_known, start_index, messages, stopped)
