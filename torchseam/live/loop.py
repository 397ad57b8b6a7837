"""The live loop: frame -> feature point -> 3D -> torch frame -> IPI plan -> gate -> EGM.

One :class:`LiveLoop` per camera. Call :meth:`LiveLoop.start` on a clean (arc-off) frame, then
:meth:`LiveLoop.on_frame` for every frame (``None`` for a frame that did not arrive). It locates
the seam, keeps the located points in the bounded look-ahead buffer, and whenever the torch
has closed in on its current target it plans the next IPI step (2 mm), builds the torch frame
from ECAL's arms, and hands the pose to the EGM link, which runs the reachability gate and its
own safety checks before anything reaches the robot.

It never moves blind, and it never stalls silently:

- **One rule for moving without evidence.** Evidence is a frame whose feature point was
  ``tracked`` (the frame's own TIPM corner confirmed it) and located (ECAL's arms seen). The
  loop moves only while its newest evidence is at most ``max_blind_ms`` old (the look-ahead
  buffer holds the seam seen up to ~20 mm ahead, so it keeps welding through a short glare),
  and hands the link that evidence's time as the measurement time: the link's age limit
  (``safety.max_age_ms``) follows from the same budget (:func:`link_max_age_ms`,
  :func:`egm_config_for`); a link that would refuse what the loop allows is a
  :class:`~torchseam.core.config.ConfigError` when the loop is built.
- **Holds are explicit.** When the budget runs out, when nothing can be planned, after
  ``max_refusals`` refusals in a row, or when the torch stops following its targets (no
  ``stall_mm`` of progress in ``stall_ms``: the link holding the robot, a silent controller) the
  loop *holds*: state ``hold``, the reason in :attr:`LiveLoop.message` and counted by key in
  :attr:`LoopStats.hold_reasons`, the arc off (:attr:`LiveLoop.arc_ok`: a torch standing still
  with the arc on burns through), and the link told to hold the robot on the last pose it sent
  (``clear_measurement``).
- **Resuming re-plans from the robot.** A held loop waits for the robot to stand still
  (``settle_mm`` in a frame) and for evidence, then plans from where the robot actually is (the
  pose the link holds it on), so its first step is one the link accepts; it tries at most once
  every ``retry_ms``. State ``resuming`` (arc still off) until the torch is seen to follow
  (``stall_mm``), then tracking with the arc on again.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import time
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum
from itertools import islice
from pathlib import Path
from typing import Any, Protocol, SupportsIndex, TypeVar, overload

import numpy as np
from scipy.spatial import cKDTree

from torchseam.core.config import CellConfig, ConfigError, config_path, load_config
from torchseam.core.config import config_field as _f
from torchseam.core.transforms import (
    axis_rotation,
    matrix_to_quat,
    quat_angle_deg,
    quat_to_matrix,
    slerp,
)
from torchseam.geometry.ecal import Ecal
from torchseam.geometry.torch_frame import frame_from_arms
from torchseam.live.locate import Location, SeamLocator
from torchseam.plan.path import LookAheadBuffer, PlanConfig, ipi_step
from torchseam.robot.egm import Verdict
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import FrameTracker
from torchseam.vision.tipm import Tipm


@dataclass(frozen=True)
class DemoFaults:
    """How ``torchseam demo --fault packet-loss`` loses EGM cycles (``demo`` in
    ``configs/live.yaml``): a fraction of the controller's datagrams, in random bursts
    (:class:`~torchseam.robot.sim_controller.BurstLoss`)."""

    packet_loss_fraction: float = _f(lo=0.0, hi=0.9)
    packet_loss_burst_cycles: float = _f(lo=1.0)


@dataclass(frozen=True)
class LiveConfig:
    """Live-loop settings (``configs/live.yaml``)."""

    lead_mm: float = _f(lo=0.0, lo_open=True)          # send the next target this close
    max_blind_ms: float = _f(lo=0.0, lo_open=True)     # move at most this long after evidence
    max_turn_deg: float = _f(lo=0.0, lo_open=True)     # largest torch rotation between targets
    max_offset_mm: float = _f(lo=0.0, lo_open=True)    # largest target distance from the path
    max_refusals: int = _f(lo=1)                       # refusals in a row that hold the loop
    stall_ms: float = _f(lo=0.0, lo_open=True)         # no progress for this long: hold
    stall_mm: float = _f(lo=0.0, lo_open=True)         # ... progress is this much towards it
    settle_mm: float = _f(lo=0.0, lo_open=True)        # held robot standing: moved less a frame
    retry_ms: float = _f(lo=0.0)                       # a held loop tries at most this often
    timing_window: int = _f(lo=1)      # per-stage timings kept (bounded)
    history: int = _f(lo=1)            # commands kept in LiveLoop.commands (bounded)
    # where the seam turns faster than max_turn_deg a step, the step shortens down to this
    min_step_mm: float = _f(default=1.0, lo=0.0, lo_open=True)
    demo: DemoFaults = _f(default=DemoFaults(0.1, 4.0))  # the demo's simulated packet loss

    def _check(self) -> None:
        if self.timing_window < 1 or self.history < 1:
            raise ValueError("timing_window and history must be >= 1")


def link_max_age_ms(live: LiveConfig, frame_rate_hz: float) -> float:
    """The age limit (``safety.max_age_ms``) of the EGM link a :class:`LiveLoop` drives.

    The loop hands the link the time of its newest evidence and decides once per frame whether
    it may still move (``max_blind_ms``); a pose it sent stands until the next frame, and the
    camera's clock jitters. So the link must accept measurements up to ``max_blind_ms`` plus one
    and a half frame periods old: with less it refuses, and holds the robot on, what the loop
    still allows (a stall); more would let it guide on older evidence than the loop's rule.
    """
    return float(live.max_blind_ms) + 1.5e3 / float(frame_rate_hz)


def egm_config_for(egm: Any, live: LiveConfig, frame_rate_hz: float) -> Any:
    """``egm`` (an :class:`~torchseam.robot.egm.config.EgmConfig`) with the age limit the live
    loop's budget implies (:func:`link_max_age_ms`): build the link a loop drives from this."""
    return dataclasses.replace(egm, safety=dataclasses.replace(
        egm.safety, max_age_ms=link_max_age_ms(live, frame_rate_hz)))


def check_link_budget(sink: Any, live: LiveConfig, frame_rate_hz: float) -> None:
    """Refuse a sink (an EGM link) whose age limit is shorter than the loop's budget needs.

    Raises:
        ConfigError: the link's ``safety.max_age_ms`` is below :func:`link_max_age_ms`.
    """
    safety = getattr(getattr(sink, "config", None), "safety", None)
    age = getattr(safety, "max_age_ms", None)
    if not isinstance(age, (int, float)):
        return  # not an EGM link (a recording sink, a test double): no age limit to match
    need = link_max_age_ms(live, frame_rate_hz)
    if age < need - 1e-9:
        raise ConfigError(
            f"the EGM link's safety.max_age_ms ({age:g} ms, configs/egm.yaml) is shorter than "
            f"the live loop's budget needs: max_blind_ms {live.max_blind_ms:g} ms "
            f"(configs/live.yaml) + 1.5 frames at {frame_rate_hz:g} Hz = {need:g} ms. The link "
            "would refuse poses the loop still sends (the robot stands still with the arc on); "
            f"set max_age_ms to {need:g} or build the link from "
            "torchseam.live.loop.egm_config_for(egm, live, frame_rate_hz)")


def check_link_turn(sink: Any, live: LiveConfig) -> None:
    """Refuse a sink (an EGM link in pose mode) that refuses the turns the loop plans.

    Raises:
        ConfigError: the loop's ``max_turn_deg`` exceeds the link's ``safety.max_step_deg``.
    """
    cfg = getattr(sink, "config", None)
    step = getattr(getattr(cfg, "safety", None), "max_step_deg", None)
    if not isinstance(step, (int, float)) or getattr(cfg, "mode", "pose") != "pose":
        return
    if live.max_turn_deg > step:
        raise ConfigError(
            f"the live loop's max_turn_deg ({live.max_turn_deg:g}, configs/live.yaml) exceeds "
            f"the EGM link's safety.max_step_deg ({step:g}, configs/egm.yaml): the link would "
            "refuse the turns the loop plans. Where the seam turns fast the loop shortens its "
            "step (min_step_mm) instead")


#: A target with no buffered point within this ahead of it lies at a hole of the look-ahead
#: (the points come ~0.3 mm apart at weld speed): its frame is interpolated across the hole
#: (LiveLoop._next)
HOLE_MM = 1.0

_T = TypeVar("_T")


class History(deque[_T]):
    """A bounded history (a ``deque`` with ``maxlen``) that also takes slices, as a list does:
    ``history[k:]`` is a list of the entries from position ``k`` on."""

    def __init__(self, items: Iterable[_T] = (), maxlen: int | None = None) -> None:
        super().__init__(items, maxlen)

    @overload
    def __getitem__(self, i: SupportsIndex, /) -> _T: ...
    @overload
    def __getitem__(self, i: slice, /) -> list[_T]: ...
    def __getitem__(self, i: SupportsIndex | slice, /) -> _T | list[_T]:  # noqa: E301
        if isinstance(i, slice):
            start, stop, step = i.indices(len(self))
            if step == 1:
                return list(islice(self, start, max(start, stop)))
            return list(self)[i]
        return super().__getitem__(i)


#: Where the seam's own frame turns more than ``max_turn_deg`` over an IPI step, the step is
#: shortened (to ``min_step_mm`` at least) so that the seam turns this share of ``max_turn_deg``
#: per target: the rest lets a torch that lags (a clamped noisy frame) catch up (LiveLoop._pose)
TURN_SHARE = 0.8


def _turn_limited(q_prev: np.ndarray | None, q: np.ndarray, max_deg: float) -> np.ndarray:
    """Slerp from ``q_prev`` towards ``q`` by at most ``max_deg`` (quaternions (4,) w, x, y,
    z, same hemisphere): the torch turns to a newly seen frame over several steps."""
    if q_prev is None:
        return q
    ang = quat_angle_deg(q_prev, q)
    if ang <= max_deg:
        return q
    return slerp(q_prev, q, max_deg / ang)


def _blend(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """Unit rows ``(1 - w) a + w b`` of two (n, 3) arrays of unit rows (a row that is not
    finite in one of them is taken from the other)."""
    out = (1.0 - w) * a + w * b
    out = np.where(np.isfinite(a).all(axis=1, keepdims=True), out, b)
    out = np.where(np.isfinite(b).all(axis=1, keepdims=True), out, a)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def load_live_config(path: str | Path | None = None) -> LiveConfig:
    return load_config(LiveConfig, path or config_path("live.yaml"))


class LoopState(str, Enum):
    STARTING = "starting"
    TRACKING = "tracking"
    COASTING = "coasting"
    HOLD = "hold"
    RESUMING = "resuming"   # after a hold: moving again from where the robot is, arc off
    DONE = "done"


class PoseSink(Protocol):
    """What the loop sends poses to (the EGM link in pose mode)."""

    def set_target(self, position_mm: Any, quaternion: Any, measured_at: float | None = None
                   ) -> Verdict: ...


def checked_verdict(verdict: object) -> Verdict:
    """A sink's answer as a :class:`Verdict`; anything else (None, a bool, an object that
    merely has an ``ok``) is a refusal: on the safety path nothing counts as accepted by
    default."""
    if isinstance(verdict, Verdict):
        return verdict
    return Verdict(False, "no_verdict",
                   f"the pose sink answered {type(verdict).__name__}, not a Verdict: refused")


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
    """What the loop counted (all since it was built).

    Attributes:
        frames / dropped_frames: frames handed in / of them ``None``.
        sent: poses the sink accepted.
        refused: poses the sink refused, by reason (the link's key: ``stale``, ``gate``, ...).
        holds: times the loop went into hold; ``hold_reasons``: the same by reason key
            (``blind``, ``plan``, ``refused``, ``stalled``, ``controller_silent``); a hold whose
            resumption failed (the torch did not follow) is still the same hold.
        resumed: holds the loop came back from (the torch followed its targets again).
        held_s: time spent held or resuming (arc off), s.
        unconfirmed: located points dropped because no evidence followed them within
            ``max_blind_ms`` (a coast that never re-acquired in time).
    """

    frames: int = 0
    dropped_frames: int = 0
    sent: int = 0
    refused: Counter = field(default_factory=Counter)
    holds: int = 0
    hold_reasons: Counter = field(default_factory=Counter)
    resumed: int = 0
    held_s: float = 0.0
    unconfirmed: int = 0
    timings_ms: dict[str, deque] = field(default_factory=dict)

    def add_time(self, stage: str, ms: float, maxlen: int) -> None:
        self.timings_ms.setdefault(stage, deque(maxlen=maxlen)).append(ms)


class LiveLoop:
    """Seeing, planning and commanding for one sensor (see the module docstring).

    Args:
        cell: calibration and process settings.
        tracker: the feature-point tracker (EAKF-STC by default in the demo).
        sink: where poses go (:class:`~torchseam.robot.egm.EgmLink` in pose mode; its
            ``safety.max_age_ms`` must cover the loop's budget, see :func:`check_link_budget`).
        plan / live: settings (``configs/plan.yaml`` / ``configs/live.yaml``; the demo hands
            each segment its weld plan's :meth:`~torchseam.plan.weld.WeldPlan.plan_config`).
        tipm / ecal: the seam locator's TIPM and ECAL (:class:`SeamLocator`).
        nominal: (N, 3) the programmed (design) path, densely sampled (mm, base). A target
            farther than ``max_offset_mm`` from it is not sent: the tracker has left the seam
            (a box tracker sliding along the stripe, say) and the loop holds.
        open_loop: nothing moves (a replay): no stall check, a held loop resumes without
            waiting for the robot to stand still, and the sink is not told to hold.

    Raises:
        ConfigError: the sink's age limit is shorter than the loop's budget needs.
    """

    def __init__(self, cell: CellConfig, tracker: FrameTracker, sink: PoseSink,
                 plan: PlanConfig, live: LiveConfig, tipm: Tipm, ecal: Ecal,
                 nominal: np.ndarray | None = None, open_loop: bool = False) -> None:
        self.cell = cell
        self.plan = plan
        self.cfg = live
        check_link_budget(sink, self.cfg, cell.process.frame_rate_hz)
        check_link_turn(sink, self.cfg)
        self.locator = SeamLocator(cell, tracker, tipm, ecal)
        self.sink = sink
        self.open_loop = open_loop
        self.nominal = None if nominal is None else np.asarray(nominal, float)
        # nearest programmed point per target in ~10 us (a dense path has thousands)
        self._nominal_tree = None if nominal is None else cKDTree(self.nominal)
        self.buffer = LookAheadBuffer(self.plan.buffer_points, self.plan.smooth_mm,
                                      outlier_mm=self.plan.outlier_mm)
        self.stats = LoopStats()
        self.state = LoopState.STARTING
        self.target: np.ndarray | None = None
        self.last_q: np.ndarray | None = None   # (4,) w, x, y, z of the last accepted pose
        # the seam's own frame at the last accepted target (the pose before the turn limit;
        # None when unknown: at the start, after a hold), for the seam's turn rate (_pose)
        self.want_q: np.ndarray | None = None
        self.evidence_t = float("-inf")  # time of the newest frame with evidence (see module)
        self.last_frame_t = float("inf")  # time of the newest frame that arrived
        # the loop lets the arc burn (False while held or resuming: the torch stands still or
        # has not yet been seen to follow); a weld's own approach is the caller's business
        self.arc_ok = True
        self.hold_key = ""               # why the current (or last) hold began
        self.hold_since = float("nan")   # when it began (frame time, s)
        # the recent commands (bounded: ``history`` in configs/live.yaml); a caller that needs
        # every command collects StepReport.command itself
        self.commands: History[Command] = History(maxlen=self.cfg.history)
        self.message = ""
        self._tilt = (axis_rotation(0, self.plan.work_angle_deg)
                      @ axis_rotation(1, self.plan.travel_angle_deg))
        # prepare()'s pose: (the buffer's answer it came from, last_q then, the pose (ip, q,
        # the seam's frame there))
        self._prepared: tuple[tuple[np.ndarray, np.ndarray | None, np.ndarray] | None,
                              np.ndarray | None,
                              tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        self._refusal_run = 0
        self._torch_prev: np.ndarray | None = None   # torch position at the previous frame
        self._t_prev = float("nan")
        # progress towards the target: (since when, closest distance then); None: none due
        self._progress: tuple[float, float] | None = None
        self._link_seen: dict[str, Any] | None = None  # the link's counters when it slowed
        self._try_t = float("-inf")      # when a held loop last tried to move
        self._resume_from: np.ndarray | None = None  # torch position when resuming began
        self._note = ""  # a message for this frame only (the resumption)
        # located points of coasting frames since the last evidence: (p, q, t, guessed)
        self._pending: list[tuple[np.ndarray, np.ndarray, float, bool]] = []
        # answers read off the look-ahead buffer at one of its versions (_next, _seen_time)
        self._hole_cache: tuple[Any, tuple, Any] | None = None
        self._seen_cache: tuple[tuple, float] | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self, frame: np.ndarray, T_B_W: np.ndarray, uv0: np.ndarray | None = None,
              t_s: float | None = None) -> None:
        """Start on a clean frame with the torch at ``T_B_W`` (4, 4) mm: TIPM finds the
        stripe's feature point, or ``uv0`` (2,) gives it. ``t_s``: the frame's time (the
        start frame is the first evidence; without it the first tracked frame is)."""
        self.locator.start(frame, uv0)
        self.last_frame_t = float("-inf") if t_s is None else float(t_s)
        self.evidence_t = float("-inf") if t_s is None else float(t_s)
        self.target = np.asarray(T_B_W, float)[:3, 3].copy()
        self.last_q = matrix_to_quat(np.asarray(T_B_W, float)[:3, :3])
        self.want_q = None
        self._prepared = None
        self.state = LoopState.TRACKING
        self.arc_ok = True

    def finish(self) -> None:
        self.state = LoopState.DONE

    # ------------------------------------------------------------------ per frame
    def on_frame(self, frame: np.ndarray | None, T_B_F: np.ndarray, T_B_W: np.ndarray,
                 t_s: float) -> StepReport:
        """One camera frame (``None``: it did not arrive) taken with the flange at ``T_B_F``;
        ``T_B_W`` is the torch's actual pose now, ``t_s`` the frame time (link clock)."""
        t0 = time.perf_counter()
        # no garbage-collection pause between the frame and its command (one landed there
        # on ~1 % of the demo's frames, 1-5 ms each): the collector runs after the command
        gc_on = gc.isenabled()
        if gc_on:
            gc.disable()
        try:
            cmd, loc, new, late, t1, t2 = self._frame_to_command(frame, T_B_F, T_B_W, t_s)
        finally:
            if gc_on:
                gc.enable()
        if late:
            self._push(new)
        self.stats.add_time("plan+gate+send", (t2 - t1) * 1e3, self.cfg.timing_window)
        self.stats.add_time("frame->command", (t2 - t0) * 1e3, self.cfg.timing_window)
        self.prepare()  # the next target, while the camera exposes the next frame
        self.stats.add_time("prepare", (time.perf_counter() - t2) * 1e3, self.cfg.timing_window)
        return StepReport(self.state, loc, cmd, self.message)

    def _frame_to_command(self, frame: np.ndarray | None, T_B_F: np.ndarray,
                          T_B_W: np.ndarray, t_s: float
                          ) -> tuple[Command | None, Location | None,
                                     list[tuple[np.ndarray, np.ndarray, float, bool]], bool,
                                     float, float]:
        """:meth:`on_frame` up to the command: ``(command, location, the frame's points for
        the buffer, whether they go in after the command, time before planning, time after
        the command)``."""
        self.stats.frames += 1
        loc = None
        if frame is None:
            self.stats.dropped_frames += 1
        else:
            self.last_frame_t = t_s
            loc = self.locator.step(frame, T_B_F)
            for k, v in loc.timings_ms.items():
                self.stats.add_time(k, v, self.cfg.timing_window)
        # a point counts as located only with the stripe seen around it (ECAL's arms):
        # a coasting filter's guess over a dark or blinded frame is not a seam point
        located = loc is not None and bool(
            np.isfinite(loc.p).all() and loc.status != TrackStatus.LOST and loc.arms_ok)
        # A point the tracker only coasted through (no evidence on its frame) waits until the
        # next evidence confirms the track again, and joins the buffer then; a coast longer
        # than max_blind_ms is never confirmed: its points are dropped, and the torch later
        # bridges the hole between seam seen with evidence on either side (a point located on
        # a frame with the laser off, say, sat alone in such a hole, and bent the fit there by
        # 5 degrees).
        new: list[tuple[np.ndarray, np.ndarray, float, bool]] = []
        seen = loc if located else None
        if seen is not None and seen.status == TrackStatus.TRACKED:
            self.evidence_t = t_s
            new, self._pending = [*self._pending, (seen.p, seen.q, t_s, seen.arms_fallback)], []
        elif seen is not None and (t_s - self.evidence_t) * 1e3 <= self.cfg.max_blind_ms:
            self._pending.append((seen.p, seen.q, t_s, seen.arms_fallback))
        elif self._pending and (t_s - self.evidence_t) * 1e3 > self.cfg.max_blind_ms:
            self.stats.unconfirmed += len(self._pending)
            self._pending = []
        # The frame's points join the buffer after the frame's command, which rests on the
        # plan prepare() made between frames from the points located before. The stripe is
        # ~20 mm ahead of the torch, so a new point reaches the fit at the next target only at
        # a segment's start; entered first, it made those commands re-plan and re-gate on the
        # frame (~1 % of frames, the slowest: 3-5 ms of plan). With nothing buffered yet there
        # is nothing else to plan from: they go in first.
        late = len(self.buffer) > 0
        if not late:
            self._push(new)
        t1 = time.perf_counter()
        cmd = self._command(np.asarray(T_B_W, float), t_s, loc)
        if self._note:
            if self.state != LoopState.HOLD:
                self.message = self._note
            self._note = ""
        t2 = time.perf_counter()
        return cmd, loc, new, late, t1, t2

    def _push(self, points: list[tuple[np.ndarray, np.ndarray, float, bool]]) -> None:
        for p, q, t, guessed in points:
            self.buffer.push(p, q, t, guessed=guessed)

    def _command(self, T_B_W: np.ndarray, t_s: float, loc: Location | None) -> Command | None:
        """Plan and send, or hold, or try to resume (see the module docstring). The
        measurement time handed to the link is that of the newest evidence (not of the
        target's own frame, which is a look-ahead older): how fresh the tracking is."""
        if self.state in (LoopState.DONE, LoopState.STARTING) or self.target is None:
            return None
        torch_p = T_B_W[:3, 3]
        moved = (math.inf if self._torch_prev is None
                 else float(np.linalg.norm(torch_p - self._torch_prev)))
        if self.state in (LoopState.HOLD, LoopState.RESUMING) and math.isfinite(self._t_prev):
            self.stats.held_s += max(0.0, t_s - self._t_prev)
        self._torch_prev, self._t_prev = torch_p.copy(), t_s
        if self.state == LoopState.HOLD:
            return self._resume(T_B_W, t_s, loc, moved)
        blind = self._blind(t_s, loc)
        if blind:
            self._hold("blind", blind, t_s)
            return None
        if self.state == LoopState.RESUMING and (
                self.open_loop or np.linalg.norm(torch_p - self._resume_from)
                >= self.cfg.stall_mm):
            self._resumed(t_s, loc)  # the torch follows again: the arc may burn
        if not self.open_loop:
            stall = self._stalled(torch_p, t_s)
            if stall is not None:
                self._hold(*stall, t_s)
                return None
        if np.linalg.norm(torch_p - self.target) > self.cfg.lead_mm:
            # on its way to the current target: re-send it with the evidence's time, which
            # keeps the link's watchdog fed
            verdict = checked_verdict(self.sink.set_target(self.target, self.last_q,
                                                           measured_at=self.evidence_t))
            if verdict.ok:
                self._refusal_run = 0
                self._set_state(loc)
            else:
                self._refused(verdict, t_s)
            return None
        pose = self._pose(self._next(self.target))
        if isinstance(pose, str):
            self._hold("plan", pose, t_s)
            return None
        return self._send(pose, torch_p, t_s, loc)

    def _send(self, pose: tuple[np.ndarray, np.ndarray, np.ndarray], torch_p: np.ndarray,
              t_s: float, loc: Location | None) -> Command:
        """Hand a new target to the sink; on acceptance it becomes the target."""
        ip, q, want = pose
        seen = self._seen_time(ip)
        verdict = checked_verdict(self.sink.set_target(ip, q, measured_at=self.evidence_t))
        ok_v = verdict.ok
        reason = verdict.detail or verdict.reason
        cmd = Command(t_s, ip, q, ok_v, reason, seen)
        self.commands.append(cmd)
        if ok_v:
            self.stats.sent += 1
            self.target = ip
            self.last_q = q
            self.want_q = want
            self._refusal_run = 0
            self._progress = (t_s, float(np.linalg.norm(torch_p - ip)))
            self._link_seen = None
            self._set_state(loc)
        else:
            self._refused(verdict, t_s)
        return cmd

    def _blind(self, t_s: float, loc: Location | None) -> str:
        """Why the loop may not move now ('' when it may): its newest evidence is older than
        ``max_blind_ms`` (the one rule, see the module docstring)."""
        age_ms = (t_s - self.evidence_t) * 1e3
        if age_ms <= self.cfg.max_blind_ms:
            return ""
        if not math.isfinite(age_ms):
            return "no tracked feature point yet: refusing to move blind"
        gap_ms = (t_s - self.last_frame_t) * 1e3
        if loc is None and gap_ms >= 0.5 * self.cfg.max_blind_ms:
            return (f"no camera frame for {gap_ms:.0f} ms (max_blind_ms "
                    f"{self.cfg.max_blind_ms:g}): holding")
        return (f"no tracked feature point for {age_ms:.0f} ms (max_blind_ms "
                f"{self.cfg.max_blind_ms:g}): refusing to move blind")

    def _stalled(self, torch_p: np.ndarray, t_s: float) -> tuple[str, str] | None:
        """``(key, why)`` when the torch has not followed its target for ``stall_ms``."""
        if self._progress is None:
            return None
        since, best = self._progress
        d = float(np.linalg.norm(torch_p - self.target))
        if d <= best - self.cfg.stall_mm or d <= 0.5 * self.cfg.stall_mm:
            self._progress = (t_s, min(best, d))  # following (or arrived)
            self._link_seen = None
            return None
        waited_ms = (t_s - since) * 1e3
        if waited_ms >= 0.5 * self.cfg.stall_ms and self._link_seen is None:
            self._link_seen = self._link_counters()  # to tell the cause if it goes on
        if waited_ms < self.cfg.stall_ms:
            return None
        return self._stall_reason(waited_ms, best - d)

    def _link_counters(self) -> dict[str, Any]:
        """The sink's counters that tell why a robot does not move ({} without any). Read
        only when the torch has stopped following (a copy of the link's statistics)."""
        st = getattr(self.sink, "stats", None)
        if st is None or not hasattr(st, "received"):
            return {}
        return {"received": st.received, "refused": Counter(st.refused),
                "holds": Counter(st.holds)}

    def _stall_reason(self, waited_ms: float, progress_mm: float) -> tuple[str, str]:
        now, then = self._link_counters(), self._link_seen or {}
        if now and then:
            if now["received"] == then["received"]:
                return ("controller_silent",
                        f"no EGM datagram from the controller for {waited_ms / 2:.0f}+ ms: "
                        "the robot stands still; holding, arc off")
            refused = now["refused"] - then["refused"]
            if refused:
                key, n = refused.most_common(1)[0]
                for k, v in refused.items():
                    self.stats.refused[k] += v
                return ("refused", f"the link refused the pose {n} times ({key}): the robot "
                                   "stands still; holding, arc off")
            holds = now["holds"] - then["holds"]
            if holds:
                key = holds.most_common(1)[0][0]
                return ("stalled", f"the link holds the robot ({key}): the torch moved "
                                   f"{max(progress_mm, 0.0):.2f} mm in {waited_ms:.0f} ms; "
                                   "holding, arc off")
        return ("stalled", f"the torch moved {max(progress_mm, 0.0):.2f} mm towards its target "
                           f"in {waited_ms:.0f} ms: holding, arc off")

    def _refused(self, verdict: Verdict, t_s: float) -> None:
        """A pose the sink refused: counted; ``max_refusals`` in a row hold the loop."""
        key = verdict.reason or "refused"
        self.stats.refused[key] += 1
        self._refusal_run += 1
        if self._refusal_run >= self.cfg.max_refusals:
            detail = verdict.detail
            self._hold("refused", f"link refused the pose {self._refusal_run} times in a row "
                                  f"({key}{': ' + detail if detail else ''}): holding, arc off",
                       t_s)
        else:
            self.message = f"link refused the pose ({key})"

    def _resume(self, T_B_W: np.ndarray, t_s: float, loc: Location | None,
                moved: float) -> Command | None:
        """A held loop: once the robot stands still, a frame has evidence and ``retry_ms``
        have passed since the last try, plan from the robot's actual pose and send."""
        if (t_s - self._try_t) * 1e3 < self.cfg.retry_ms - 1e-6:
            return None
        if not self.open_loop and moved > self.cfg.settle_mm:
            return None  # the robot still finishes its last step
        if self.evidence_t != t_s:
            return None  # the cause has not cleared: no tracked point in this frame
        self._try_t = t_s
        # where the robot actually is: the pose the link holds it on, the reference of the
        # link's next step check
        self.target = T_B_W[:3, 3].copy()
        q = matrix_to_quat(T_B_W[:3, :3])
        if self.last_q is not None and q @ self.last_q < 0:
            q = -q
        self.last_q = q
        self.want_q = None
        self._prepared = None
        pose = self._pose(self._next(self.target))
        if isinstance(pose, str):
            return None
        cmd = self._send(pose, T_B_W[:3, 3], t_s, None)
        if cmd.ok:
            self.state = LoopState.RESUMING
            self._resume_from = T_B_W[:3, 3].copy()
            self.message = f"resuming from where the robot is (held: {self.hold_key})"
        return cmd

    def _resumed(self, t_s: float, loc: Location | None) -> None:
        self.stats.resumed += 1
        self.arc_ok = True
        held = t_s - self.hold_since
        self.state = LoopState.TRACKING  # _set_state refines it below when a frame came
        self._set_state(loc)
        self._note = f"resumed after {held:.2f} s held ({self.hold_key}); arc on"

    def _next(self, cp: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray] | None:
        """The look-ahead buffer's IPI step from ``cp`` (``(ip, tangent, arm directions)``),
        never backwards, and bridged across a hole.

        Where the torch moved without locating anything (a blind stretch: the stripe passed
        over seam it could not see, and the robot finished its last step after the hold) the
        buffer has a hole, which the torch reaches ~20 mm later. In a hole wider than two steps
        the buffered point nearest ``cp`` lies behind it, and the buffer's search, which starts
        there, steps back, then forward again, for ever: a step that does not advance along
        the torch's travel direction is replaced by one towards the first buffered point at
        least a step ahead (within the distance a blind stretch can open: ``max_blind_ms`` at
        weld speed plus three steps). A target inside a hole takes its seam direction and arms
        interpolated between the fits on either side of the hole (the fit ahead alone is the
        seam up to a few mm further on, where the saddle has turned the joint's bisector by
        1-2 degrees)."""
        step = self.cell.process.step_mm
        nxt = self.buffer.next_command(cp, step)
        if nxt is None or self.last_q is None:
            return nxt
        x = quat_to_matrix(self.last_q)[:, 0]  # the travel direction (torch frame x)
        if float((nxt[0] - cp) @ x) <= 0.0:
            nxt = self._step_ahead(cp, x, step)
            if nxt is None:
                return None
        # the frame that finds the torch at its target asks what prepare() asked between
        # frames: the same answer while the buffer has not changed (its version)
        key = (self.buffer.version, len(self.buffer), x.tobytes())
        hole = self._hole_cache
        if hole is not None and hole[0] is nxt and hole[1] == key:
            return hole[2]
        out = self._across_hole(nxt, x)
        self._hole_cache = (nxt, (self.buffer.version, len(self.buffer), x.tobytes()), out)
        return out

    def _step_ahead(self, cp: np.ndarray, x: np.ndarray, step: float
                    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray] | None:
        """IPI step towards the first unflagged buffered point a step or more ahead of ``cp``
        along ``x`` (None: none within reach)."""
        pts = self.buffer.points
        P = np.array([loc.p for loc in pts])
        reach = self.cell.process.weld_speed_mm_s * self.cfg.max_blind_ms / 1e3 + 3.0 * step
        ok = ((P - cp) @ x >= step) & (np.linalg.norm(P - cp, axis=1) <= reach)
        for k in np.flatnonzero(ok):
            if pts[k].flagged:
                continue
            p, tangent, arms = self.buffer.fit(int(k))  # judges the window's points
            if not pts[k].flagged:
                return ipi_step(cp, p, step), tangent, arms
        return None

    def _across_hole(self, nxt: tuple[np.ndarray, np.ndarray | None, np.ndarray],
                     x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """``nxt`` unchanged unless its target lies in or at a hole of the buffer (no point
        within ``HOLE_MM`` ahead of it: its fit, taken at the next point a step from the last
        target, lies across the hole): then its tangent and arms interpolated between the
        fits at the nearest points behind and ahead of it, and the target moved onto the curve
        through both (sideways only: its progress along the travel direction stays)."""
        ip = nxt[0]
        pts = self.buffer.points
        P = np.array([loc.p for loc in pts])
        along = (P - ip) @ x
        flagged = np.array([loc.flagged for loc in pts])
        behind = np.flatnonzero((along < 0) & ~flagged)
        ahead = np.flatnonzero((along > 0) & ~flagged)
        if not len(behind) or not len(ahead) or float(
                np.min(np.linalg.norm(P[ahead] - ip, axis=1))) <= HOLE_MM:
            return nxt  # seen right ahead of the target: the buffer's own fit holds
        kb, ka = int(behind[np.argmax(along[behind])]), int(ahead[np.argmin(along[ahead])])
        pb, tb, arms_b = self.buffer.fit(kb)
        pa, ta, arms_a = self.buffer.fit(ka)
        w = float(-along[kb] / (along[ka] - along[kb]))  # 0 at the point behind, 1 ahead
        arms = _blend(arms_b, arms_a, w)
        tangent = nxt[1]
        if tb is not None and ta is not None:
            tangent = _blend(tb[None], ta[None], w)[0]
            # on the curve through both sides (cubic Hermite from their points and tangents),
            # not on the chord towards the far side (0.2 mm inside the saddle over 10 mm)
            span = float(np.linalg.norm(pa - pb))
            h = ((2 * w**3 - 3 * w**2 + 1) * pb + (w**3 - 2 * w**2 + w) * span * tb
                 + (-2 * w**3 + 3 * w**2) * pa + (w**3 - w**2) * span * ta)
            ip = h + ((ip - h) @ x) * x  # across the seam from the curve, along it as planned
        return ip, tangent, arms

    def _pose(self, nxt: tuple[np.ndarray, np.ndarray | None, np.ndarray] | None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
        """The next target pose ``(ip (3,), q (4,), the seam's frame at ip (4,))`` from the
        look-ahead buffer's IPI step ``nxt`` from the current target, or why there is none (the
        loop then holds with that message).

        The torch turns at most ``max_turn_deg`` from the last pose (q is the seam's frame
        turned towards by that much at most). Where the seam's own frame turns more than that
        over the step (a branch offset towards the main pipe's side: the seam drops round the
        flank and its frame turns up to 4.3 degrees per 2 mm; the link refuses more than its
        ``safety.max_step_deg``, 3, between two targets), the step is shortened, to
        ``min_step_mm`` at least, so that the seam turns ``TURN_SHARE * max_turn_deg`` per
        target: the torch keeps up with the seam's turn (up to ``max_turn_deg / min_step_mm``
        degrees per mm) instead of lagging it. The target and the frame there are interpolated
        between the current target and the full step's (the seam bends by ~0.01 mm over 2 mm:
        one fit serves both)."""
        if nxt is None:
            return "nothing located a step ahead of the torch"
        ip, tangent, arms = nxt
        prep = self._prepared
        if prep is not None and prep[0] is nxt and prep[1] is self.last_q:
            return prep[2]  # prepare() made this pose from this very answer and last pose
        if tangent is None:
            # too little of the seam seen to fit its direction (the start of a segment): keep
            # the torch's present travel direction rather than guess from a chord
            assert self.last_q is not None  # set by start()
            tangent = quat_to_matrix(self.last_q)[:, 0]
        if self._nominal_tree is not None:
            off = float(self._nominal_tree.query(ip)[0])
            if off > self.cfg.max_offset_mm:
                return (f"target {off:.1f} mm off the programmed path (limit "
                        f"{self.cfg.max_offset_mm:g} mm): tracking suspect")
        if not np.all(np.isfinite(arms)):
            return "no arm points (ECAL) near the target: no torch frame"
        facing = None if self.last_q is None else quat_to_matrix(self.last_q)[:, 2]
        R, ok = frame_from_arms(ip, ip + arms[0], ip + arms[1], tangent, facing)
        if not ok:
            return "degenerate torch frame (arms collinear)"
        q = matrix_to_quat(R @ self._tilt)
        if self.last_q is not None and q @ self.last_q < 0:
            q = -q  # the sign nearest the previous pose: the controller turns the short way
        ip, q = self._shortened(ip, q)
        return ip, _turn_limited(self.last_q, q, self.cfg.max_turn_deg), q

    def _shortened(self, ip: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ip, q)``, or the shorter step towards them where the seam's frame turns faster
        than ``max_turn_deg`` over the step (see :meth:`_pose`)."""
        w, cp = self.want_q, self.target
        if w is None or cp is None:
            return ip, q
        turn = quat_angle_deg(w, q)
        if turn <= self.cfg.max_turn_deg:
            return ip, q
        d = float(np.linalg.norm(ip - cp))
        f = max(TURN_SHARE * self.cfg.max_turn_deg / turn, self.cfg.min_step_mm / max(d, 1e-9))
        if f >= 1.0:
            return ip, q
        qs = slerp(w, q, f)
        if qs @ q < 0:
            qs = -qs
        return cp + f * (ip - cp), qs

    def prepare(self) -> None:
        """Work between frames: the tracker's learning for the next frame (its ``idle()``),
        and the plan of the target after the current one (the look-ahead
        buffer's seam fit) and let the sink's gate check its pose, so that the frame which
        finds the torch at its target only has to send. Changes no decision: the buffer drops
        the plan when a new point could change it and the gate re-checks a pose that differs
        (:meth:`LookAheadBuffer.prepare`, :meth:`ReachGate.prepare`). ``on_frame`` calls
        this after the frame's command is out; it is timed as the ``prepare`` stage. A held
        loop plans nothing ahead (it re-plans from the robot when it resumes)."""
        idle = getattr(self.locator.tracker, "idle", None)
        if idle is not None:
            idle()  # the tracker's learning for the next frame (EAKF-STC's context model)
        if self.state in (LoopState.DONE, LoopState.STARTING, LoopState.HOLD) or (
                self.target is None):
            return
        self.buffer.prepare(self.target, self.cell.process.step_mm)
        nxt = self._next(self.target)
        self._prepared = None
        pose = self._pose(nxt)
        if isinstance(pose, str):
            return
        self._prepared = (nxt, self.last_q, pose)
        self._seen_time(pose[0])  # kept for the frame that sends it (_seen_cache)
        ready = getattr(self.sink, "prepare", None)
        if ready is not None:
            ready(pose[0], pose[1])

    def _seen_time(self, ip: np.ndarray) -> float:
        """When the buffered point nearest ``ip`` was seen (one vectorised search: a norm
        per point cost ~0.3 ms a command with the ~100 points of the look-ahead)."""
        pts = self.buffer.points
        if not pts:
            return float("nan")
        key = (self.buffer.version, len(pts), np.asarray(ip, float).tobytes())
        if self._seen_cache is not None and self._seen_cache[0] == key:
            return self._seen_cache[1]  # (prepare() made this pose: the sink's prepare asked)
        P = np.array([loc.p for loc in pts])
        t = pts[int(np.argmin(np.einsum("ij,ij->i", P - ip, P - ip)))].t_s
        self._seen_cache = (key, t)
        return t

    def _hold(self, key: str, why: str, t_s: float) -> None:
        """Hold: no new target, the arc off, the link told to hold the robot on the last pose
        it sent; ``key`` counts the hold in ``stats.hold_reasons``. A hold that began before
        (the loop was resuming and the torch did not follow) goes on as the same hold."""
        if self.state not in (LoopState.HOLD, LoopState.RESUMING):
            self.stats.holds += 1
            self.stats.hold_reasons[key] += 1
            self.hold_key, self.hold_since = key, t_s
            self._try_t = t_s
        self.state = LoopState.HOLD
        self.message = why
        self.arc_ok = False
        self._refusal_run = 0
        self._progress = None
        self._link_seen = None
        self._prepared = None
        clear = getattr(self.sink, "clear_measurement", None)
        if clear is not None and not self.open_loop:
            clear()  # the link holds the robot from its next cycle (no stale refusals)
        return None

    def _set_state(self, loc: Location | None) -> None:
        if loc is None or self.state == LoopState.RESUMING:
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
