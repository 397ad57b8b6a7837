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

import time
from collections import Counter, deque
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from torchseam.core.config import CONFIG_DIR, CellConfig, load_config
from torchseam.core.transforms import quat_to_matrix
from torchseam.geometry.torch_frame import quaternions, tilt, torch_frame
from torchseam.live.locate import Location, SeamLocator
from torchseam.plan.path import LookAheadBuffer, PlanConfig, load_plan_config
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import FrameTracker


@dataclass(frozen=True)
class LiveConfig:
    """Live-loop settings (``configs/live.yaml``)."""

    lead_mm: float             # send the next target when the torch is this close to the last
    max_blind_mm: float        # travel allowed past the last trusted measurement
    max_turn_deg: float        # largest torch rotation between two targets
    max_offset_mm: float       # largest distance of a target from the programmed path
    max_frame_gap_ms: float    # no camera frame for longer than this: hold
    timing_window: int         # per-stage timings kept (bounded)


def _turn_limited(q_prev: torch.Tensor | None, q: torch.Tensor, max_deg: float
                  ) -> torch.Tensor:
    """Slerp from ``q_prev`` towards ``q`` by at most ``max_deg`` (quaternions w, x, y, z,
    same hemisphere): the torch turns to a newly seen frame over several steps."""
    if q_prev is None:
        return q
    d = float(torch.clamp(torch.dot(q_prev, q), -1.0, 1.0))
    ang = 2.0 * float(np.degrees(np.arccos(abs(d))))
    if ang <= max_deg:
        return q
    f = max_deg / ang
    half = np.arccos(abs(d))
    out = (np.sin((1 - f) * half) * q_prev + np.sign(d) * np.sin(f * half) * q) / np.sin(half)
    return out / out.norm()


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
        self.buffer = LookAheadBuffer(self.plan.buffer_points, self.plan.smooth_mm)
        self.stats = LoopStats()
        self.state = LoopState.STARTING
        self.target: np.ndarray | None = None
        self.last_q: torch.Tensor | None = None
        self.last_trusted: np.ndarray | None = None
        self.fresh_t = float("-inf")   # time of the newest frame the tracker followed
        self.last_frame_t = float("inf")  # time of the newest frame that arrived
        self.commands: list[Command] = []
        self.message = ""

    # ------------------------------------------------------------------ lifecycle
    def start(self, frame: np.ndarray, T_B_W: np.ndarray) -> None:
        """Start on a clean frame with the torch at ``T_B_W``: TIPM finds the stripe."""
        self.locator.start(frame)
        self.last_frame_t = float("-inf")
        self.target = np.asarray(T_B_W, float)[:3, 3].copy()
        self.last_q = quaternions(torch.tensor(np.asarray(T_B_W, float)[None, :3, :3]))[0]
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
            if np.all(np.isfinite(loc.p)) and loc.status != TrackStatus.LOST and loc.arms_ok:
                self.buffer.push(loc.p, loc.q, t_s)
                self.fresh_t = t_s
                if loc.status == TrackStatus.TRACKED:
                    self.last_trusted = loc.p
        t1 = time.perf_counter()
        cmd = self._command(T_B_W[:3, 3], t_s, loc)
        t2 = time.perf_counter()
        self.stats.add_time("plan+gate+send", (t2 - t1) * 1e3, self.cfg.timing_window)
        self.stats.add_time("frame->command", (t2 - t0) * 1e3, self.cfg.timing_window)
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
                self.sink.set_target(self.target, self.last_q.numpy(), measured_at=self.fresh_t)
                self._set_state(loc)
            return None
        nxt = self.buffer.next_command(self.target, self.cell.process.step_mm)
        if nxt is None:
            return self._hold("nothing located a step ahead of the torch")
        ip, tangent, arms = nxt
        if tangent is None:
            # too little of the seam seen to fit its direction (the start of a segment): keep
            # the torch's present travel direction rather than guess from a chord
            tangent = quat_to_matrix(self.last_q.numpy())[:, 0]
        if self.last_trusted is None or self._beyond(ip, self.last_trusted, tangent,
                                                      self.cfg.max_blind_mm):
            return self._hold(f"no trusted measurement within {self.cfg.max_blind_mm:g} mm "
                              "ahead: refusing to move blind")
        if self.nominal is not None:
            off = float(np.min(np.linalg.norm(self.nominal - ip, axis=1)))
            if off > self.cfg.max_offset_mm:
                return self._hold(f"target {off:.1f} mm off the programmed path (limit "
                                  f"{self.cfg.max_offset_mm:g} mm): tracking suspect")
        if not np.all(np.isfinite(arms)):
            return self._hold("no arm points (ECAL) near the target: no torch frame")
        P = torch.tensor(ip)[None]
        R, ok = torch_frame(P, P + torch.tensor(arms[0])[None], P + torch.tensor(arms[1])[None],
                            tangent=torch.tensor(tangent)[None])
        if not bool(ok[0]):
            return self._hold("degenerate torch frame (arms collinear)")
        R = tilt(R, self.plan.work_angle_deg, self.plan.travel_angle_deg)
        q = _turn_limited(self.last_q, quaternions(R, previous=self.last_q)[0],
                          self.cfg.max_turn_deg)
        seen = self._seen_time(ip)
        verdict = self.sink.set_target(ip, q.numpy(), measured_at=self.fresh_t)
        ok_v = bool(getattr(verdict, "ok", True))
        reason = getattr(verdict, "detail", "") or getattr(verdict, "reason", "")
        cmd = Command(t_s, ip, q.numpy(), ok_v, reason, seen)
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

    @staticmethod
    def _beyond(ip: np.ndarray, ref: np.ndarray, tangent: np.ndarray, margin: float) -> bool:
        """ip lies more than ``margin`` past ref along the travel direction."""
        return float((ip - ref) @ tangent) > margin

    def _seen_time(self, ip: np.ndarray) -> float:
        if not self.buffer.points:
            return float("nan")
        return min(self.buffer.points, key=lambda L: float(np.linalg.norm(L.p - ip))).t_s

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
