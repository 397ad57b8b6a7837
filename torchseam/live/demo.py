"""``torchseam demo``: weld a simulated part (the T joint by default) in closed loop, six
segments, with a report.

The weld follows the part's weld plan: :func:`~torchseam.plan.preflight.preflight` runs first
(every pose of every segment, approach included, through the reachability gate the live loop
uses) and chooses the part's placement on the positioner, where the six segments start and the
torch's work and travel angles per segment (the configured plan when it passes, else a searched
one). A part the robot cannot weld is refused before anything moves (:class:`PlanRefused`, whose
text is the pre-flight table with the refused segments and the reason; ``torchseam demo`` prints
it and exits with 2).

Each segment runs through the same runner as ``torchseam weld``
(:func:`~torchseam.live.runner.run_segment`: the start, the travel, the arc's strike rule, the
gaps, the operator's hold and stop, the events), with the simulated cell in this process as its
cell: per frame (25 Hz of simulation time) the simulator renders what the sensor sees from
where the simulated robot actually is, with the arc the runner asked for; the live loop tracks,
locates, plans and hands torch poses to the EGM link; ten 4 ms EGM cycles move the simulated
IRC5 (lockstep, see :mod:`torchseam.live.simcell`). The part carries the deviations of
``--part`` and arc noise of ``--noise``. Faults (``--fault``) are injected in the middle of
each segment (packet loss: over the whole segment, a fraction of the EGM cycles in random
bursts, ``demo`` in ``configs/live.yaml``).

The simulated arc follows the loop: it burns from the end of the approach on while the loop
lets it (:attr:`~torchseam.live.loop.LiveLoop.arc_ok`: off while the loop holds or resumes). A
segment whose end the torch did not reach is reported in ``summary["segments_incomplete"]``
with the reason (``torchseam demo`` then exits with 1).

No silent gap in the bead: the loop does not go back after an arc interruption (it re-strikes
where the torch is when it resumes), so the simulated cell counts the seam the torch passed with
the arc out past the approach, per segment (``summary["unwelded_mm"]``, each stretch in
``summary["arc_gaps"]`` with where it lies along the segment and when and why the arc went
out). A segment with more than :data:`MAX_GAP_MM` unwelded is not welded: it goes into
``segments_incomplete`` with the gap as its reason, even when the torch reached its end.

``summary.json`` names the run: ``part``, ``seed``, ``noise_level``, ``length_mm``,
``segments``, ``tracker``, ``model``, ``faults`` (asked) and ``faults_injected`` (each fault's
segment and time window). :func:`write_report` writes it last and atomically.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import torch

from torchseam.core.config import CellConfig, NoiseConfig, PartConfig
from torchseam.core.errors import TorchseamError
from torchseam.core.overlay import put_label
from torchseam.core.report import RUN_MARKER, report_file, write_json_atomic
from torchseam.core.transforms import apply, invert, quat_to_matrix
from torchseam.live.events import DemoControl as DemoControl  # (re-exported)
from torchseam.live.events import DemoEvent as DemoEvent
from torchseam.live.events import FrameRecord as FrameRecord
from torchseam.live.loop import (
    Command,
    LiveConfig,
    LiveLoop,
    LoopState,
    StepReport,
    egm_config_for,
)
from torchseam.live.names import FAULTS as FAULTS  # the faults run_demo injects (re-exported)
from torchseam.live.parts import LiveParts
from torchseam.live.ring import torch_axis_errors
from torchseam.live.runner import MAX_GAP_MM as MAX_GAP_MM  # (re-exported)
from torchseam.live.runner import (
    MOVING_FRACTION,
    MOVING_WINDOW_S,
    ArcGapMeter,
    CellFrame,
    SegmentJob,
    run_segment,
)
from torchseam.live.search import (
    SeamSearch,
    SearchConfig,
    across_seam,
    choose_standoff,
    offset_pose,
    search_start,
    steps_between,
)
from torchseam.live.simcell import LockstepCell, SimClock
from torchseam.plan.path import PlanConfig
from torchseam.plan.preflight import PlanReport, preflight
from torchseam.plan.weld import SegmentPlan, WeldPlan
from torchseam.robot.egm import EgmConfig, EgmLink
from torchseam.robot.egm.messages import EgmSensor
from torchseam.robot.reach import ReachGate
from torchseam.sim.scene import Scene
from torchseam.sim.sequence import SensorRenderer
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import make_tracker
from torchseam.vision.profiles import ProfileFinder

FAULT_FRAMES = 30          # how long each fault lasts, frames (1.2 s); packet loss: the segment
POSES_CSV_HEADER = "t,x,y,z,q1,q2,q3,q4"  # poses.csv: what ``torchseam robot check`` reads
# the demo skips the positioner's turn and the torch's return between two segments (its clock
# does not move); poses.csv counts this much time for each, so that its time stamps are ones
# a robot can keep (the return is a joint move of tens of degrees)
TRANSFER_S = 5.0


@dataclass
class DemoResult:
    frames: list[FrameRecord] = field(default_factory=list)
    # every pose the link accepted: (segment, p (3,), q (4,), seen_t_s, command t_s)
    sent: list[tuple[str, np.ndarray, np.ndarray, float, float]] = field(default_factory=list)
    # per pose sent with the arc on (not the approach), torch axis vs the true bisector
    axis_deg: list[float] = field(default_factory=list)
    refused: dict[str, int] = field(default_factory=dict)
    watchdog_trips: int = 0
    quats: dict[str, np.ndarray] = field(default_factory=dict)
    paths: dict[str, list[np.ndarray]] = field(default_factory=dict)
    latency: dict[str, tuple[float, float]] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    # segments not welded to their end: {"segment": name, "reason": why}
    incomplete: list[dict[str, str]] = field(default_factory=list)
    holds: int = 0                       # loop holds, all segments
    hold_reasons: dict[str, int] = field(default_factory=dict)
    loop_refused: dict[str, int] = field(default_factory=dict)  # refusals the loop saw
    arc_off_s: float = 0.0               # past the approach with the arc held off by the loop
    arc_interruptions: int = 0           # times the loop put the arc out past the approach
    wire_unsafe: int = 0                 # poses on the wire (link -> robot) that fail a re-check
    part: PartConfig | None = None       # the part welded, and its pose in the base per segment
    part_poses: dict[str, np.ndarray] = field(default_factory=dict)  # (turned by the positioner)
    report: PlanReport | None = None     # the weld plan followed and its pre-flight
    # per segment started off the seam (start_offset_mm/start_angle_deg): the search for it
    searches: list[dict] = field(default_factory=list)
    # per segment welded: seam passed past the approach, and of it with the arc out (mm)
    passed_mm: dict[str, float] = field(default_factory=dict)
    unwelded_mm: dict[str, float] = field(default_factory=dict)
    # each stretch of seam passed with the arc out: segment, from_mm / to_mm along it,
    # length_mm, arc_out_t_s (None: before the arc first struck), cause
    arc_gaps: list[dict] = field(default_factory=list)
    # each fault as injected: segment, fault, from_t_s, to_t_s, frames
    faults_injected: list[dict] = field(default_factory=list)


class PlanRefused(TorchseamError):
    """The pre-flight found poses of the part's weld plan that the robot cannot weld: nothing
    moved. ``report`` is the pre-flight; the message is its text (the table names each refused
    segment, its first refused pose and the reason)."""

    def __init__(self, report: PlanReport) -> None:
        self.report = report
        super().__init__(report.text() + "\nnothing moved: the demo welds a part only when the "
                         "pre-flight passes every pose of its plan")

    def summary_line(self) -> str:
        """One line: which part, which segments, the first reason."""
        r = self.report
        v = next(v for v in r.verdicts if not v.passed)
        return (f"the robot cannot weld {r.part_name}: pre-flight refused segment(s) "
                f"{', '.join(r.refused)} ({v.reason}); nothing moved")


class _WireTap:
    """The link as the simulated controller sees it: every reply passes through, and each
    pose that differs from the previous reply is kept (what the robot was commanded)."""

    def __init__(self, link: EgmLink) -> None:
        self.link = link
        self.poses: list[tuple[np.ndarray, np.ndarray]] = []
        self._last: tuple[float, ...] | None = None   # the last reply's pose, as floats

    def handle_datagram(self, data: bytes, sender) -> bytes | None:
        reply = self.link.handle_datagram(data, sender)
        if reply is not None:
            msg = EgmSensor()
            msg.ParseFromString(reply)
            c = msg.planned.cartesian
            pq = (c.pos.x, c.pos.y, c.pos.z, c.orient.u0, c.orient.u1, c.orient.u2,
                  c.orient.u3)
            # (compared value by value, as np.array_equal of the two arrays would)
            if self._last is None or any(a != b for a, b in zip(pq, self._last, strict=True)):
                self.poses.append((np.array(pq[:3]), np.array(pq[3:])))
            self._last = pq
        return reply

    def __getattr__(self, name: str):
        return getattr(self.link, name)


def run_demo(cell: CellConfig, part: PartConfig, noise: NoiseConfig, level: float, seed: int,
             faults: tuple[str, ...] = (), segments: str = "abcdef", tracker: str = "anchored",
             video: cv2.VideoWriter | None = None, progress=None,
             length_mm: float | None = None,
             observer: Callable[[DemoEvent], None] | None = None,
             control: DemoControl | None = None,
             model_path: str | Path | None = None,
             report: PlanReport | None = None,
             part_name: str = "part",
             start_offset_mm: float = 0.0, start_angle_deg: float = 0.0, *,
             parts: LiveParts) -> DemoResult:
    """Weld the ring; returns everything the report needs. ``length_mm`` welds only the first
    mm of each segment (quick runs and tests). ``observer`` is called once per frame with a
    :class:`DemoEvent`; ``control`` lets an operator hold, resume or stop the weld.
    ``parts``: the settings and parts of the run (:class:`~torchseam.live.parts.LiveParts`;
    :func:`~torchseam.live.parts.load_live_parts` reads the shipped ones): ``parts.live`` is
    the loop's settings (its ``demo`` section sets the packet loss), ``parts.egm`` the link's
    and the simulated controller's, ``parts.robot`` the gate's arm. The link's age limit
    follows from the loop's budget
    (:func:`~torchseam.live.loop.egm_config_for`). ``model_path``: the EAKF-STC model file of
    the ``eakf-stc`` / ``anchored`` trackers (default the shipped one).

    The weld follows ``part``'s weld plan: ``report`` (a
    :func:`~torchseam.plan.preflight.preflight` of ``part``; default: run here, ``part_name``
    names the part in its table) gives the placement (``report.plan.part`` is the part welded),
    the segments' starts and each segment's torch work and travel angles.

    Start off the seam: with ``start_offset_mm`` or ``start_angle_deg`` non-zero each segment
    starts from its programmed start pose moved ``start_offset_mm`` across the seam along the
    part's surface on that side (:meth:`~torchseam.plan.weld.WeldPlan.search_arms`: along the
    main body or the plate, or up the branch; + is the torch frame's y side), lifted back along
    the torch axis by the search stand-off and turned ``start_angle_deg`` about the torch axis.
    The stand-off is the lowest of ``parts.search`` at which every
    pose of the search region passes the reachability gate with the torch's tip off the part
    (:func:`~torchseam.live.search.choose_standoff`). A
    :class:`~torchseam.live.search.SeamSearch` then moves the torch, arc off, in a bounded
    zig-zag around that start until TIPM confirms the stripe's corner; the corner is
    triangulated with the cell's calibration (as the live loop does) and an approach (arc off,
    steps the link accepts, every pose through the gate) brings the torch onto the seam point
    it found: the programmed start moved by the found point's offset across the programmed
    path (at most ``max_seam_offset_mm``), and the loop's programmed path with it. The weld
    then goes on as without a start offset. The search's and the approach's frames are
    recorded (states ``search``, ``approach``; in the video too). Not found within the bound:
    the segment is incomplete with the search's reason (``summary["search"]`` has each search;
    ``search_time_s``, ``search_frames``).

    Raises:
        PlanRefused: the pre-flight refused a pose of the plan (any segment: a ring is not
            started that cannot be closed); nothing moved.
        TorchseamError: the plan rolls the torch about its axis (the live loop applies work
            and travel angles only; ``search.roll_deg`` in configs/plan.yaml is [0, 0]).
    """
    plan, live = parts.plan, parts.live
    report = _passed_preflight(cell, part, parts, report, part_name, segments)
    weld_plan = report.plan
    writer = _VideoThread(video) if video is not None else None
    run = _Run(cell=cell, part=weld_plan.part,  # placed as planned
               noise=noise, level=level, seed=seed, faults=faults, tracker=tracker,
               model_path=model_path, live=live, plan=plan, weld_plan=weld_plan,
               egm=_demo_egm_config(cell, live, parts.egm), length_mm=length_mm,
               start_offset_mm=start_offset_mm, start_angle_deg=start_angle_deg, parts=parts,
               observer=observer, control=control, progress=progress, writer=writer,
               res=DemoResult(part=weld_plan.part, report=report),
               segments_asked=segments)
    try:
        for seg in weld_plan.segments:
            if seg.name in segments:
                run.segment(seg)
    finally:
        if writer is not None:
            writer.close()
    return run.finish()


def _passed_preflight(cell: CellConfig, part: PartConfig, parts: LiveParts,
                      report: PlanReport | None, part_name: str, segments: str) -> PlanReport:
    """The pre-flight of ``part`` (``report``, or run here): raises :class:`PlanRefused` when
    it refused a pose, :class:`TorchseamError` when the plan rolls the torch on a segment to
    weld."""
    if report is None:
        report = preflight(cell, part, config=parts.plan, robot=parts.robot,
                           part_name=part_name)
    if not report.ok:
        raise PlanRefused(report)
    rolled = [s.name for s in report.plan.segments if s.name in segments and s.roll_deg]
    if rolled:
        raise TorchseamError(
            f"the weld plan of {report.part_name} rolls the torch about its axis on segment(s) "
            f"{', '.join(rolled)}: the live loop applies work and travel angles only (keep "
            "search.roll_deg at [0, 0] in configs/plan.yaml)")
    return report


def _demo_egm_config(cell: CellConfig, live: LiveConfig, egm: EgmConfig) -> EgmConfig:
    """``egm`` as the demo's link runs it: pose mode, the loop's age limit, a step check the
    IPI step passes, the simulated controller moving at weld speed."""
    proc = cell.process
    egm = egm_config_for(egm, live, proc.frame_rate_hz)
    # the IPI step must pass the link's step check; the controller moves at weld speed
    safety = dataclasses.replace(egm.safety,
                                 max_step_mm=max(egm.safety.max_step_mm, 1.25 * proc.step_mm))
    return dataclasses.replace(
        egm, mode="pose", safety=safety,
        sim_controller=dataclasses.replace(egm.sim_controller,
                                           tcp_speed_mm_s=proc.weld_speed_mm_s))


@dataclass
class _Start:
    """Where a segment starts: the programmed start pose (``search`` None) or a pose off the
    seam (``search``: the settings of the search for it, ``across``: the move across the seam,
    ``lift``: the stand-off)."""

    T: np.ndarray
    search: SearchConfig | None = None
    across: Callable[[float], np.ndarray] | None = None
    lift: float = 0.0


@dataclass
class _Run:
    """One :func:`run_demo`: its settings, the simulated clock and what it has gathered."""

    cell: CellConfig
    part: PartConfig
    noise: NoiseConfig
    level: float
    seed: int
    faults: tuple[str, ...]
    tracker: str
    model_path: str | Path | None
    live: LiveConfig
    plan: PlanConfig
    weld_plan: WeldPlan
    egm: EgmConfig
    length_mm: float | None
    start_offset_mm: float
    start_angle_deg: float
    parts: LiveParts
    observer: Callable[[DemoEvent], None] | None
    control: DemoControl | None
    progress: Callable[[int], object] | None
    writer: _VideoThread | None
    res: DemoResult
    segments_asked: str = "abcdef"  # the segments asked for
    clock: SimClock = field(default_factory=SimClock)
    latency: dict[str, list[float]] = field(default_factory=dict)
    unsafe: int = 0
    stopped: bool = False

    @property
    def stopped_by(self) -> str:
        return self.control.stopped_by if self.control is not None else "the operator"

    @property
    def dt(self) -> float:
        return 1.0 / self.cell.process.frame_rate_hz

    def segment(self, seg: SegmentPlan) -> None:
        """Weld one segment (or record why it was not) and add up its figures."""
        res = self.res
        if self.stopped or (self.control is not None and self.control.stopped):
            self.stopped = True
            res.incomplete.append({"segment": seg.name,
                                   "reason": f"not welded: stopped by {self.stopped_by}"})
            return
        scene = Scene(self.part, seg.rotation_deg)  # the part as planned, turned for seg
        res.part_poses[seg.name] = scene.T_B_Tnom
        gate = ReachGate(self.parts.robot, cell=self.cell, part=self.part,
                         part_pose_mm=scene.T_B_Tnom)
        s0 = float(scene.s_at(np.array([seg.phi_start]))[0])
        seg_len = (float(scene.s_at(np.array([seg.phi_end]))[0]) - s0) % scene.seam_length_mm
        if self.length_mm is not None:
            seg_len = min(seg_len, self.length_mm)
        approach = self.cell.process.look_ahead_mm + self.plan.approach_mm
        # the programmed start pose, with the segment's torch angles
        T0 = self.weld_plan.nominal_tcp(seg, np.array([s0 - approach]))[0]
        start = self._start(seg, gate, T0, s0 - approach)
        if start is None:
            return  # the gate refused the start pose: nothing moved
        w = _SegmentWeld(self, seg, scene, gate, s0, seg_len, approach, T0, start)
        w.weld()
        self._account(w)

    def _start(self, seg: SegmentPlan, gate: ReachGate, T0: np.ndarray, u0: float
               ) -> _Start | None:
        """The segment's start: ``T0``, or off the seam (``start_offset_mm`` /
        ``start_angle_deg``) at the lowest stand-off at which the whole search region clears
        the part (the gate, and the torch's tip); None (recorded) when the gate refuses it."""
        offset_mm, angle_deg = self.start_offset_mm, self.start_angle_deg
        if not (offset_mm or angle_deg):
            return _Start(T0)
        res, clock = self.res, self.clock
        scfg = self.parts.search
        # across the seam along the part's surfaces
        across = across_seam(*self.weld_plan.search_arms(seg, u0))
        lift, n_ok, n_all = choose_standoff(T0, scfg, offset_mm, angle_deg,
                                            partial(_search_clear, gate), across)
        T_start = search_start(T0, lift, offset_mm, angle_deg, across)
        v = gate.check(torch.tensor(T_start[None]))
        tip = float(gate.tip_clearance(T_start)[0])
        margin = gate.config.clearance.margin_mm
        refused = not bool(v.ok[0]) or tip < margin
        if not refused:
            return _Start(T_start, scfg, across, lift)
        because = v.reasons[0] if not bool(v.ok[0]) else (
            f"the torch's tip {tip:.1f} mm from the part < {margin:g}")
        why = (f"start pose refused: {offset_mm:g} mm / {angle_deg:g} "
               f"deg off the seam at a {lift:g} mm stand-off, the reachability "
               f"gate refuses it ({because}); nothing moved in this segment")
        res.searches.append({"segment": seg.name, "found": False, "reason": why,
                             "time_s": 0.0, "extent_mm": 0.0, "extent_deg": 0.0,
                             "gate_refused": 1, "standoff_mm": lift,
                             "region_clear": f"{n_ok}/{n_all}"})
        res.incomplete.append({"segment": seg.name, "reason": why})
        res.messages.append(f"[{seg.name} t={clock.t:.2f}s] segment incomplete: {why}")
        return None

    def _account(self, w: _SegmentWeld) -> None:
        """Add a welded segment's poses, statistics and paths to the result."""
        res, seg, loop, link = self.res, w.seg, w.loop, w.link
        for name, times in loop.stats.timings_ms.items():
            self.latency.setdefault(name, []).extend(times)
        sent = [c for c in w.commands if c.ok]
        for c in sent:
            res.sent.append((seg.name, c.p, c.q, c.seen_t_s, c.t_s))
        # (in the approach the torch turns from the programmed orientation onto the
        # seam's, at most max_turn_deg a step: up to ~5 degrees off, arc off)
        weld = [c for c, arc in zip(w.commands, w.welding, strict=True) if c.ok and arc]
        if weld:
            res.axis_deg += list(torch_axis_errors(
                w.scene, np.array([c.p for c in weld]),
                quat_to_matrix(np.array([c.q for c in weld])),
                np.array([c.seen_t_s for c in weld]), angles=seg.angles[:2])[0])
        # the link's count: new targets and the re-sends that keep its watchdog fed
        link_stats = link.stats
        _add_counts(res.refused, link_stats.refused)
        res.watchdog_trips += link_stats.watchdog_trips
        st = loop.stats
        res.holds += st.holds
        _add_counts(res.hold_reasons, st.hold_reasons)
        _add_counts(res.loop_refused, st.refused)
        if link_stats.refused:
            res.messages.append(
                f"[{seg.name} t={self.clock.t:.2f}s] the link refused "
                f"{sum(link_stats.refused.values())} pose(s): " + ", ".join(
                    f"{r} {n}" for r, n in link_stats.refused.most_common()))
        res.quats[seg.name] = np.array([c.q for c in sent]).reshape(-1, 4)
        res.paths.setdefault("tracked", []).append(np.array([c.p for c in sent]).reshape(-1, 3))
        res.paths.setdefault("nominal", []).append(w.scene.nominal_tcp(
            w.s0 + np.arange(0.0, w.seg_len, self.cell.process.step_mm))[:, :3, 3])
        res.paths.setdefault("true seam", []).append(
            _true_curve(w.scene, self.clock.t, w.s0, w.seg_len))
        self.unsafe += _unsafe(sent, w.gate, None)
        wire = [Command(0.0, p, q, True, "", 0.0) for p, q in w.tap.poses]
        res.wire_unsafe += _unsafe(wire, w.gate, self.egm.safety.max_step_mm)

    def finish(self) -> DemoResult:
        """The result with its latency and summary."""
        res = self.res
        res.latency = {k: (float(np.percentile(v, 50)), float(np.percentile(v, 99)))
                       for k, v in self.latency.items() if v}
        res.summary = _summary(res, self.unsafe + res.wire_unsafe)
        res.summary["stopped"] = self.stopped
        if res.searches:
            res.summary["search"] = list(res.searches)
            # time to find the seam (s of simulated time, the longest of the segments'
            # searches) and the frames the search and its approach took (in the video, state
            # search/approach)
            found = [r["time_s"] for r in res.searches if r["found"]]
            res.summary["search_time_s"] = max(found) if found else None
            res.summary["search_frames"] = sum(f.state in ("search", "approach")
                                               for f in res.frames)
        res.summary["plan"] = self.weld_plan.to_dict()
        res.summary.update(self._identity())
        return res

    def _identity(self) -> dict:
        """What was welded and how: the part, the seed, the noise, the length, the tracker and
        its model, every fault asked and where it was injected."""
        rep = self.res.report
        return {
            "part": rep.part_name if rep is not None else None,
            "seed": int(self.seed), "noise_level": float(self.level),
            "segments": "".join(s.name for s in self.weld_plan.segments
                                if s.name in self.segments_asked),
            "length_mm": self.length_mm, "tracker": self.tracker,
            "model": _model_used(self.tracker, self.model_path),
            "start_offset_mm": self.start_offset_mm, "start_angle_deg": self.start_angle_deg,
            "faults": list(self.faults), "faults_injected": list(self.res.faults_injected),
            "max_gap_mm": MAX_GAP_MM,
        }


def _model_used(tracker: str, model_path: str | Path | None) -> str | None:
    """The model file the tracker read (None: a tracker without a fitted model)."""
    from torchseam.track import model_file

    if model_path is not None:
        return str(model_path)
    if tracker == "anchored":
        return str(model_file.DEFAULT_MODEL)
    if tracker == "eakf-stc":
        return (str(model_file.EAKF_STC_MODEL) if model_file.EAKF_STC_MODEL.is_file()
                else "built-in EAKF-STC defaults")
    return None


def _add_counts(total: dict[str, int], counts: Mapping[str, int]) -> None:
    for key, n in counts.items():
        total[key] = total.get(key, 0) + n


class _SegmentWeld:
    """One segment of a :class:`_Run`: the simulated cell from its start pose, the seam search
    when it starts off the seam, then the live loop's frames to the segment's end."""

    def __init__(self, run: _Run, seg: SegmentPlan, scene: Scene, gate: ReachGate, s0: float,
                 seg_len: float, approach: float, T0: np.ndarray, start: _Start) -> None:
        self.run, self.seg, self.scene, self.gate = run, seg, scene, gate
        self.s0, self.seg_len, self.approach, self.T0, self.start = (
            s0, seg_len, approach, T0, start)
        cell, proc, dt = run.cell, run.cell.process, run.dt
        self.link = EgmLink(run.egm, gate=gate, clock=run.clock, bind=False)
        self.tap = _WireTap(self.link)
        # (the tap is the link as the controller sees it: it forwards what it is not)
        self.simcell = LockstepCell(cell, run.egm, self.tap, run.clock,  # type: ignore[arg-type]
                                    start.T, robot=gate.robot)
        if "packet-loss" in run.faults:
            self.simcell.ctrl.set_loss(run.live.demo.packet_loss_fraction,
                                       run.live.demo.packet_loss_burst_cycles,
                                       run.seed * 10 + seg.index)
        self.renderer = SensorRenderer(cell, scene, run.noise, run.level,
                                       run.seed * 10 + seg.index)
        self.ref = _SeamRef(scene)
        self.nominal = scene.nominal_tcp(s0 - approach + np.arange(
            0.0, approach + seg_len + 10.0, 0.5))[:, :3, 3]
        self.n_max = int((approach + seg_len) / (proc.weld_speed_mm_s * dt) * 1.6) + 50
        self.frame_mm = proc.weld_speed_mm_s * dt   # the torch's travel in a frame
        self.fault_at = int((approach + 0.5 * seg_len) / (proc.weld_speed_mm_s * dt))
        self.commands: list[Command] = []  # every pose handed to the link (the loop keeps few)
        self.welding: list[bool] = []      # the arc was on when it was handed over
        self.search_failed = ""
        self.start_p, self.start_along = T0[:3, 3], 0.0
        self.injected: dict[str, list[float]] = {}   # fault -> [from_t_s, to_t_s, frames]

    def weld(self) -> None:
        run, seg = self.run, self.seg
        if self.start.search is not None:
            self._search(self.start.search)
        tipm = run.parts.tipm
        # the part's joint decides what is tracked (a fillet: run.tracker; else its profile)
        tracker = (make_tracker(run.tracker, tipm, model_path=run.model_path)
                   if run.part.joint == "fillet"
                   else run.parts.tracker(run.tracker, run.part.joint, run.model_path))
        self.loop = LiveLoop(run.cell, tracker,
                             self.link, run.weld_plan.plan_config(seg, run.plan), run.live,
                             tipm, run.parts.ecal, nominal=self.nominal)
        job = SegmentJob(seg.name, self.approach, self.seg_len, self.frame_mm, run.dt,
                         self.simcell.tool_inv, start_along_mm=self.start_along)
        self.cell = cell = _SimulatedCell(self)
        done = run_segment(cell, self.loop, job, control=run.control, observer=run.observer,
                           link=self.link, messages=run.res.messages)
        self.commands += done.commands
        self.welding += done.welding
        run.res.arc_off_s += done.arc_off_s
        run.res.arc_interruptions += done.arc_interruptions
        run.stopped = run.stopped or done.stopped
        gap_why = cell.gap.reason()
        if not done.reached_end or gap_why:
            why = self.search_failed or (
                (_incomplete_reason(self.loop, run.stopped, done.travelled_mm, self.approach,
                                    self.seg_len, self.n_max, run.stopped_by)
                 if done.reason in ("", _SimulatedCell.OUT_OF_FRAMES) or done.stopped
                 else done.reason) if not done.reached_end else "")
            why = "; ".join(w for w in (gap_why, why) if w)
            run.res.incomplete.append({"segment": seg.name, "reason": why})
            run.res.messages.append(f"[{seg.name} t={run.clock.t:.2f}s] segment incomplete: "
                                    f"{why}")
        self._record_gaps()
        self.loop.finish()
        self.simcell.close()

    def _record_gaps(self) -> None:
        res, name, gap = self.run.res, self.seg.name, self.cell.gap
        res.passed_mm[name] = round(gap.passed_mm, 3)
        res.unwelded_mm[name] = round(gap.gap_mm, 3)
        for g in gap.stretches:
            res.arc_gaps.append({"segment": name, **g, "from_mm": round(g["from_mm"], 3),
                                 "to_mm": round(g["to_mm"], 3),
                                 "length_mm": round(g["to_mm"] - g["from_mm"], 3),
                                 "arc_out_t_s": None if g["arc_out_t_s"] is None
                                 else round(g["arc_out_t_s"], 3)})
        for f, (t0, t1, n) in self.injected.items():
            res.faults_injected.append({"segment": name, "fault": f, "from_t_s": round(t0, 3),
                                        "to_t_s": round(t1, 3), "frames": int(n)})

    def _search(self, scfg: SearchConfig) -> None:
        """Search for the seam from the start pose; when found the weld starts where it was
        found, else nothing more moves in this segment."""
        run, start = self.run, self.start
        found = _search_seam(
            self.seg.name, scfg, start.T, start.lift, start.across, run.start_offset_mm,
            run.start_angle_deg, self.gate, self.simcell, self.renderer, self.tap, run.clock,
            run.dt, self.commands, run.res, run.cell, self.ref, run.writer, self.nominal,
            self._programmed, run.plan.approach_mm, _seam_detector(run.parts, run.part.joint))
        self.welding += [False] * (len(self.commands) - len(self.welding))
        if not found["found"]:
            self.search_failed = found["reason"]
            self.n_max = 0   # nothing more moves in this segment
        else:
            # the part is where the search saw its seam: the programmed path, moved by the
            # offset found, is the one the loop's targets are held to
            shift = np.asarray(found["seam_offset_vec_mm"], float)
            self.nominal = self.nominal + shift
            self.start_along = found["start_along_mm"]
            self.start_p = self.simcell.tcp_pose()[:3, 3]

    def _programmed(self, u: float) -> np.ndarray:
        """The programmed torch pose ``u`` mm along the path from the programmed start."""
        return self.run.weld_plan.nominal_tcp(
            self.seg, np.array([self.s0 - self.approach + u]))[0]

    def _active_faults(self, k: int) -> list[str]:
        faults = self.run.faults
        active = [f for f in faults if f != "packet-loss"
                  and self.fault_at <= k < self.fault_at + FAULT_FRAMES]
        if "packet-loss" in faults:
            active.append("packet-loss")
        return active


class _SimulatedCell:
    """The simulated cell in this process, for :func:`~torchseam.live.runner.run_segment`:
    each frame rendered where the simulated robot is at its exposure, with the arc the runner
    asked for burning; the faults injected; then ten 4 ms EGM cycles in lockstep to the next
    frame. Its clock stands while the operator holds (nothing moves)."""

    OUT_OF_FRAMES = "out of frames"

    def __init__(self, w: _SegmentWeld) -> None:
        self.w, self.run = w, w.run
        self.gap = ArcGapMeter()
        self.k, self.arc = 0, False
        self.image: np.ndarray | None = None
        self.truth: Any = None
        self.active: list[str] = []
        # (t, torch position) of the last frames: is the torch moving
        self.recent: deque[tuple[float, np.ndarray]] = deque(maxlen=16)

    def next_frame(self) -> CellFrame | str | None:
        w, run, clock = self.w, self.run, self.run.clock
        if self.k >= w.n_max:
            return self.OUT_OF_FRAMES
        if self.k:
            w.simcell.advance(run.dt)
        T_B_W = w.simcell.tcp_pose()
        # (the torch came here from the last frame with the arc as the runner set it)
        self.gap.add(T_B_W[:3, 3], self.arc)
        self.recent.append((clock.t, T_B_W[:3, 3]))
        self.active = active = w._active_faults(self.k)
        for f in active:
            win = w.injected.setdefault(f, [clock.t, clock.t, 0])
            win[1], win[2] = clock.t, win[2] + 1
        self.image, self.truth = w.renderer.render(T_B_W, clock.t, arc_on=self.arc,
                                                   laser_on="laser-off" not in active,
                                                   force_flash="arc-flash" in active)
        if "controller-silence" in active:
            w.simcell.faults.silent_cycles = 10
        if run.writer is not None:
            run.writer.idle()  # the recorder finishes before the loop takes the frame
        self.k += 1
        return CellFrame(None if "dropped-frames" in active else self.image, clock.t, T_B_W)

    def torch_now(self) -> np.ndarray | None:
        return None    # lockstep: the frame's pose is where the torch is

    def moving(self) -> bool:
        t, p = self.recent[-1]
        old = [(t0, p0) for t0, p0 in self.recent if t - t0 >= MOVING_WINDOW_S - 1e-9]
        if not old:
            return True      # too early to tell: the segment's first frames
        t0, p0 = old[-1]
        v = float(np.linalg.norm(p - p0)) / (t - t0)
        return v >= MOVING_FRACTION * self.run.cell.process.weld_speed_mm_s

    def set_arc(self, on: bool) -> None:
        self.arc = on

    def hold_here(self) -> None:
        """(The simulated clock stands while held: nothing moves.)"""

    def guided(self) -> str:
        return ""

    def label(self, t_s: float | None = None) -> str:
        return f"[{self.w.seg.name} t={self.run.clock.t:.2f}s]"

    def record(self, f: CellFrame, rep: StepReport | None, arc: bool,
               along_mm: float) -> FrameRecord:
        run, w = self.run, self.w
        loc = rep.location if rep else None
        rec = _record(w.seg.name, self.truth, loc, rep, w.ref, f.t_s, f.T_B_W,
                      ",".join(self.active), arc)
        run.res.frames.append(rec)
        if run.writer is not None and self.image is not None:
            run.writer.put(self.image, self.truth, loc, rep, w.seg.name)
        if run.progress:
            run.progress(1)
        return rec


def _search_clear(gate: ReachGate, T: np.ndarray) -> np.ndarray:
    """(N,) the poses (N, 4, 4) pass the gate (each on its own: no joint speed between them)
    and the torch's tip clears the part by the gate's margin (the arc is off: nothing may
    touch the part)."""
    T = np.asarray(T, float).reshape(-1, 4, 4)
    ok = gate.check(torch.tensor(T), dt_s=_APART_S).ok.numpy()
    return ok & (gate.tip_clearance(T) >= gate.config.clearance.margin_mm)


_APART_S = 1e6   # poses checked each on its own (no joint speed from one to the next)


@dataclass
class _Seen:
    """What the video shows of a search frame: TIPM's corner (``status`` 0 when it saw one)."""

    uv: np.ndarray
    status: int


class _Found(NamedTuple):
    """What a seam search sees in a frame: whether the joint's feature is there, and where."""

    ok: bool
    uv: np.ndarray


def _seam_detector(parts: LiveParts, joint: str) -> Callable[[np.ndarray], _Found]:
    """What a seam search looks for in a whole frame: TIPM's corner (a fillet), else the
    joint profile's aim point (the gap of a butt, the root of a groove, the step of a lap)."""
    if joint == "fillet":
        tipm = parts.tipm

        def corner(frame: np.ndarray) -> _Found:
            r = tipm(frame)
            return _Found(bool(r.ok), r.uv)
        return corner
    finder = ProfileFinder(parts.tipm, parts.profiles, joint)

    def aim(frame: np.ndarray) -> _Found:
        r = finder(frame)
        return _Found(bool(r.ok), r.aim)
    return aim


def _search_seam(seg: str, cfg: SearchConfig, T_start: np.ndarray, lift: float, across,
                 offset_mm: float, angle_deg: float, gate: ReachGate, simcell: LockstepCell,
                 renderer: SensorRenderer, link, clock: SimClock, dt: float,
                 commands: list[Command], res: DemoResult, cell: CellConfig, ref: _SeamRef,
                 writer: _VideoThread | None, nominal: np.ndarray,
                 programmed: Callable[[float], np.ndarray], max_along_mm: float,
                 detect: Callable[[np.ndarray], _Found]) -> dict:
    """Search for the seam from ``T_start`` (the robot is there), arc off, then approach the
    seam point it found; every pose through ``gate`` (and, off the seam, the tip's clearance)
    and handed to ``link`` (kept in ``commands``). Each frame is recorded (state ``search``,
    then ``approach``) and goes to the video. ``detect``: what is looked for in a frame
    (:func:`_seam_detector`: TIPM's corner, or the joint profile's aim point).

    The corner (or aim point) confirmed is triangulated with the cell's calibration from the flange
    pose of its frame (as the live loop does) and placed against the programmed path
    (``nominal``, (N, 3) base mm, from the programmed start on): ``u`` mm along it, offset
    from it by ``shift``. The approach goes over that point at the stand-off ``lift`` and down
    onto it, the torch turned as programmed there (``programmed(u)``, (4, 4)); a point seen
    more than ``max_along_mm`` along the path is approached at ``max_along_mm``, moved by its
    offset (the stripe must see the seam ahead of the torch before the arc strikes). An offset
    across the path beyond ``cfg.max_seam_offset_mm`` is a failed search (another edge, or the
    wrong part). Appends the search's record to ``res.searches`` and returns it (when found,
    with ``seam_offset_vec_mm``, the offset, and ``start_along_mm``, where the weld starts
    along the programmed path)."""
    from torchseam.core.transforms import matrix_to_quat
    from torchseam.geometry.triangulate import FastTriangulator

    def reachable(T: np.ndarray) -> bool:
        return bool(_search_clear(gate, T)[0])

    def send(T: np.ndarray) -> bool:
        q = matrix_to_quat(T[:3, :3])
        v = link.set_target(T[:3, 3], q, measured_at=clock.t)
        commands.append(Command(clock.t, T[:3, 3].copy(), q, bool(v.ok), v.reason, clock.t))
        return bool(v.ok)

    nan2, nan3 = np.full(2, np.nan), np.full(3, np.nan)

    def record(state: str, uv=None, message: str = "") -> tuple:
        """Render the frame where the robot is, record it (arc off) and queue it for the
        video; returns what ``detect`` saw (None when ``uv`` is given), the TCP pose and the
        simulator's truth of the frame."""
        T_now = simcell.tcp_pose()
        frame, truth = renderer.render(T_now, clock.t, arc_on=False)
        r = detect(frame) if uv is None else None
        seen = r.uv if r is not None and r.ok else (uv if uv is not None else nan2)
        status = int(TrackStatus.TRACKED) if r is not None and r.ok else int(TrackStatus.LOST)
        res.frames.append(FrameRecord(seg, clock.t, False, np.asarray(seen, float), truth.uv,
                                      status, state, nan3, truth.seam_B,
                                      ref.distance(clock.t, T_now[:3, 3]), ""))
        if writer is not None:
            writer.idle()
            writer.put(frame, truth, _Seen(np.asarray(seen, float), status),
                       _Banner(state, message), seg)
        return r, T_now, truth

    tri = FastTriangulator(cell)
    t0 = clock.t
    lateral = None if across is None else (
        lambda y: across(offset_mm + y) - across(offset_mm))
    s = SeamSearch(T_start, cfg, 1.0 / dt, reachable, t0_s=t0, lateral=lateral)
    rec: dict = {"segment": seg, "found": False, "reason": "", "standoff_mm": lift}
    p_seen = None
    while True:
        r, T_now, truth = record("search", message=f"searching: {s.y + offset_mm:+.1f} mm, "
                                 f"{s.a + angle_deg:+.1f} deg, stand-off {lift:g} mm")
        if s.observe(r.ok, r.uv, clock.t, T_now):
            p_seen = tri(np.asarray(r.uv, float)[None], simcell.flange_pose())[0]
            # (the simulator's truth, for the record only: how far the corner located lies
            # from the true seam point on the stripe)
            rec["seen_error_mm"] = round(float(np.linalg.norm(p_seen - truth.seam_B)), 3)
            break
        T = s.step()
        if T is None:
            break
        if not send(T):
            s.failed, s.reason = True, f"the link refused a search pose ({commands[-1].reason})"
            break
        simcell.advance(dt)
    rec.update(time_s=round(clock.t - t0, 3), extent_mm=round(s.extent[0], 3),
               extent_deg=round(s.extent[1], 3), gate_refused=s.refused)
    shift, u = _place_seen(s, p_seen, nominal, cfg, rec)
    if not s.found:
        rec["reason"] = s.reason
        res.messages.append(f"[{seg} t={clock.t:.2f}s] {s.reason}")
        res.searches.append(rec)
        return rec
    assert shift is not None
    res.messages.append(f"[{seg} t={clock.t:.2f}s] seam found after {clock.t - t0:.2f} s "
                        f"({s.y + offset_mm:+.1f} mm, {s.a + angle_deg:+.1f} deg from the "
                        f"programmed start, stand-off {lift:g} mm), "
                        f"{rec['seam_offset_mm']:.1f} mm across the programmed seam, "
                        f"{u:.1f} mm along it: approaching it")
    # the approach: at the stand-off over the seam point found, then down onto it, the torch
    # turned as programmed there. (A point seen farther than max_along_mm along the path is
    # approached at max_along_mm, moved by its offset: the stripe must see the seam ahead
    # of the torch before the arc strikes.)
    t1 = clock.t
    u = min(u, max_along_mm)
    T_prog = programmed(u)
    T_seam = T_prog.copy()
    T_seam[:3, 3] += shift
    step_mm, step_deg = cfg.speed_mm_s * dt, cfg.turn_deg_s * dt
    T_last = s.pose(s.y, s.a)
    above = offset_pose(T_seam, lift_mm=lift)
    over = steps_between(T_last, above, step_mm, step_deg)
    down = steps_between(above, T_seam, step_mm, step_deg)
    for k, T in enumerate(over + down):
        # over the part the tip keeps clear of it too; the descent brings it onto the seam
        ok = reachable(T) if k < len(over) else bool(gate.check(torch.tensor(T[None])).ok[0])
        if not ok or not send(T):
            rec["reason"] = "the approach from the search to the seam was refused"
            res.messages.append(f"[{seg} t={clock.t:.2f}s] {rec['reason']}")
            res.searches.append(rec)
            return rec
        simcell.advance(dt)
        record("approach", uv=nan2, message="approach: onto the seam found "
                                            f"({rec['seam_offset_mm']:.1f} mm off the program)")
    for _ in range(int(2.0 / dt)):  # the robot arrives (it lags its targets by a few frames)
        if np.linalg.norm(simcell.tcp_pose()[:3, 3] - T_seam[:3, 3]) < 0.05:
            break
        simcell.advance(dt)
        record("approach", uv=nan2, message="approach: arriving")
    # how far from the true seam the weld starts, and how far the programmed pose there is
    at = simcell.tcp_pose()[:3, 3]
    rec.update(start_error_mm=round(ref.distance(clock.t, at), 3),
               programmed_start_error_mm=round(ref.distance(clock.t, T_prog[:3, 3]), 3))
    ref.distance(clock.t, at)   # (its look-up window back where the torch is)
    rec.update(found=True, approach_s=round(clock.t - t1, 3), start_along_mm=round(u, 3),
               seam_offset_vec_mm=[round(float(v), 4) for v in shift])
    res.searches.append(rec)
    return rec


def _place_seen(s: SeamSearch, p_seen: np.ndarray | None, nominal: np.ndarray,
                cfg: SearchConfig, rec: dict) -> tuple[np.ndarray | None, float]:
    """Where the corner a search found (``p_seen``, base mm) lies against the programmed path
    ``nominal`` ((N, 3) from the programmed start on): its offset from the path's nearest point
    and how far along the path (mm) that point is; ``(None, 0.0)`` when the search did not find
    it. A corner whose ray misses the laser plane, or that lies more than
    ``cfg.max_seam_offset_mm`` across the path, fails the search (``s.found`` False, with the
    reason); the offset across goes into ``rec["seam_offset_mm"]``."""
    if not s.found:
        return None, 0.0
    if p_seen is None or not np.all(np.isfinite(p_seen)):
        s.found, s.reason = False, "seam not found: the corner's ray misses the laser plane"
        return None, 0.0
    # the programmed path's nearest point (index i, u mm along it from the programmed
    # start) and the offset of the point found from it, across the path
    i = int(np.argmin(np.linalg.norm(nominal - p_seen, axis=1)))
    j0, j1 = max(i - 1, 0), min(i + 1, len(nominal) - 1)
    tan = nominal[j1] - nominal[j0]
    tan = tan / np.linalg.norm(tan)
    shift = p_seen - nominal[i]
    across_mm = float(np.linalg.norm(shift - (shift @ tan) * tan))
    u = float(np.linalg.norm(np.diff(nominal[:i + 1], axis=0), axis=1).sum())
    rec["seam_offset_mm"] = round(across_mm, 3)
    if across_mm > cfg.max_seam_offset_mm:
        s.found = False
        s.reason = (f"seam not found: the corner seen lies {across_mm:.1f} mm from the "
                    f"programmed seam (limit {cfg.max_seam_offset_mm:g} mm: another "
                    "edge, or the part is not where the plan puts it); nothing moved "
                    "towards it")
    return shift, u


def _incomplete_reason(loop: LiveLoop, stopped: bool, travelled: float, approach: float,
                       seg_len: float, n_max: int, stopped_by: str = "the operator") -> str:
    """Why a segment's end was not reached, in words."""
    if stopped:
        done = max(0.0, travelled - approach)
        return f"stopped by {stopped_by} after {done:.1f} of {seg_len:.1f} mm"
    done = max(0.0, travelled - approach)
    where = f"{done:.1f} of {seg_len:.1f} mm welded in {n_max} frames"
    if loop.state == LoopState.HOLD:
        return f"held ({loop.hold_key}): {loop.message}; {where}"
    if loop.state == LoopState.RESUMING:
        return f"resuming after a hold ({loop.hold_key}) when time ran out; {where}"
    return f"time ran out; {where}"


class _VideoThread:
    """Draws, scales and encodes the video on a second thread (OpenCV releases the GIL while
    it works), fed through a bounded queue: the weld hands it each frame after processing it
    and waits (:meth:`idle`) before processing the next, so it overlaps the simulator's
    rendering and the robot's motion only; every frame is kept, none pile up in memory.

    Args:
        video: an open ``cv2.VideoWriter`` for half-size frames.
        maxsize: frames queued at most.
    """

    def __init__(self, video: cv2.VideoWriter, maxsize: int = 8) -> None:
        self.video = video
        self.queue: queue.Queue[tuple | None] = queue.Queue(maxsize)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="demo-video", daemon=True)
        self.thread.start()

    def put(self, frame: np.ndarray, truth, loc, rep, seg: str) -> None:
        """Queue one frame (BGR (H, W, 3) uint8, not modified) with what to draw on it."""
        if self.error is not None:
            raise RuntimeError(f"writing the video failed: {self.error!r}")
        self.queue.put((frame, truth, loc, rep, seg))

    def idle(self) -> None:
        """Wait until every queued frame is written. The weld calls this before each frame's
        processing: the recorder then works while the simulator renders and the robot moves,
        never during the loop's frame -> command (sharing the 2-core VM with it, the encoder
        put 1.3 ms on the loop's median and 2 ms on its p99). A cell's recorder would use the
        loop's idle time between camera frames the same way."""
        self.queue.join()

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            try:
                if item is None:
                    return
                if self.error is not None:
                    continue  # keep draining so that put() never blocks for ever
                ov = _overlay(*item)
                self.video.write(cv2.resize(ov, (ov.shape[1] // 2, ov.shape[0] // 2),
                                            interpolation=cv2.INTER_AREA))
            except Exception as e:  # reported to the weld thread by the next put()
                self.error = e
            finally:
                self.queue.task_done()

    def close(self) -> None:
        """Write what is queued and stop the thread."""
        self.queue.put(None)
        self.thread.join()


def _record(seg, truth, loc, rep, ref: _SeamRef, t, T_B_W, fault, arc: bool) -> FrameRecord:
    nan2, nan3 = np.full(2, np.nan), np.full(3, np.nan)
    return FrameRecord(
        seg, t, arc, loc.uv if loc else nan2, truth.uv,
        int(loc.status) if loc else int(TrackStatus.LOST),
        rep.state.value if rep else LoopState.STARTING.value,
        loc.p if loc else nan3, truth.seam_B, ref.distance(t, T_B_W[:3, 3]), fault)


class _SeamRef:
    """The true seam of one segment's part, sampled densely once, for distance look-ups."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.curve = scene.true_joint.dense_seam().point
        self.closed = scene.true_joint.closed
        self.k: int | None = None

    def distance(self, t: float, p: np.ndarray) -> float:
        p_T = apply(invert(self.scene.part_pose(t)), p)
        if self.k is None:
            self.k = int(np.argmin(np.linalg.norm(self.curve - p_T, axis=1)))
        idx = self.k + np.arange(-200, 201)
        idx = idx % len(self.curve) if self.closed else idx[(idx >= 0) & (idx < len(self.curve))]
        d = np.linalg.norm(self.curve[idx] - p_T, axis=1)
        self.k = int(idx[np.argmin(d)])
        return float(d.min())


def _true_curve(scene: Scene, t: float, s0: float, seg_len: float) -> np.ndarray:
    phi = scene.phi_at(s0 + np.linspace(0, seg_len, 200))
    return apply(scene.part_pose(t), scene.true_joint.seam(phi).point)


def _unsafe(sent: list[Command], gate: ReachGate, max_step: float | None) -> int:
    """Re-check poses (``sent``, in order) with a fresh gate: count the ones it refuses,
    non-finite ones and, with ``max_step``, steps longer than ``max_step`` mm. The demo checks
    the poses the link accepted without the step (after a hold the loop re-plans from where
    the robot is, not from an accepted target the robot never got) and the poses the link put
    on the wire with it (what the robot was commanded, holds included)."""
    if not sent:
        return 0
    from torchseam.core.transforms import pose_matrix

    T = pose_matrix(np.array([c.p for c in sent]), np.array([c.q for c in sent]))
    bad = ~np.isfinite(T).all(axis=(1, 2))
    verdict = gate.check(torch.tensor(T[~bad]))
    steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    over = 0 if max_step is None else int((steps > max_step * (1 + 1e-9)).sum())
    return int(bad.sum() + (~verdict.ok.numpy()).sum() + over)


def _summary(res: DemoResult, unsafe: int) -> dict:
    # frames under a sensor fault are left out of the accuracy figures (packet loss does not
    # blind the sensor and lasts the whole segment: its frames count)
    fr = [f for f in res.frames if f.arc_on and f.fault in ("", "packet-loss")]
    pix = np.array([np.linalg.norm(f.uv - f.uv_true) for f in fr if np.all(np.isfinite(f.uv))])
    loc = np.array([np.linalg.norm(f.p - f.p_true) for f in fr if np.all(np.isfinite(f.p))])
    torch_err = np.array([f.torch_err_mm for f in fr])
    nominal_err: list[float] = []
    for P, C in zip(res.paths.get("nominal", []), res.paths.get("true seam", []), strict=True):
        nominal_err += [float(np.min(np.linalg.norm(C - p, axis=1))) for p in P]
    nominal = np.array(nominal_err)
    lat = res.latency.get("frame->command", (float("nan"), float("nan")))
    axis = np.array(res.axis_deg)

    def rms(x):
        return float(np.sqrt(np.mean(x**2))) if len(x) else float("nan")

    return {
        "seam_rmse_mm": rms(torch_err), "seam_max_mm": float(torch_err.max()) if len(
            torch_err) else float("nan"),
        "located_rmse_mm": rms(loc), "located_max_mm": float(loc.max()) if len(loc) else 0.0,
        "nominal_rmse_mm": rms(nominal),
        "nominal_max_mm": float(nominal.max()) if len(nominal) else float("nan"),
        "pixel_rmse_px": rms(pix), "pixel_max_px": float(pix.max()) if len(pix) else 0.0,
        "axis_rmse_deg": rms(axis), "axis_max_deg": float(axis.max()) if len(axis) else float(
            "nan"), "axis_within_1deg": int((axis <= 1.0).sum()), "poses_welded": len(axis),
        "latency_p50_ms": lat[0], "latency_p99_ms": lat[1],
        "poses_sent": len(res.sent), "poses_refused": int(sum(res.refused.values())),
        "refused_reasons": dict(res.refused),
        "watchdog_trips": int(res.watchdog_trips),
        "unsafe_poses_sent": int(unsafe),
        "frames": len(res.frames),
        "holds": int(res.holds), "hold_reasons": dict(res.hold_reasons),
        "loop_refused": dict(res.loop_refused),
        "arc_off_s": round(float(res.arc_off_s), 3),
        "arc_interruptions": int(res.arc_interruptions),
        # seam passed past the approach per segment, and of it with the arc out (a segment
        # above MAX_GAP_MM is in segments_incomplete); each such stretch in arc_gaps
        "passed_mm": dict(res.passed_mm),
        "unwelded_mm": dict(res.unwelded_mm),
        "arc_gaps": list(res.arc_gaps),
        "segments_incomplete": list(res.incomplete),
    }


@dataclass
class _Banner:
    """The state line of a frame the live loop did not see (the search, the approach)."""

    state: str
    message: str = ""


def _overlay(frame, truth, loc, rep, seg) -> np.ndarray:
    """The video frame: the corner found (colour by status) and the state line, its text over
    a dark outline (readable on a white arc flash). ``rep``: the loop's
    :class:`~torchseam.live.loop.StepReport`, a :class:`_Banner` (search frames) or None."""
    out = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame.copy()
    if loc is not None and np.all(np.isfinite(loc.uv)):
        colour = {0: (0, 255, 0), 1: (0, 200, 255), 2: (0, 0, 255)}[int(loc.status)]
        c = tuple(int(round(x)) for x in loc.uv)
        cv2.drawMarker(out, c, colour, cv2.MARKER_CROSS, 20, 2, cv2.LINE_AA)
        cv2.circle(out, c, 12, colour, 1, cv2.LINE_AA)
    if isinstance(rep, _Banner):
        state = rep.state
    else:
        state = rep.state.value if rep else "starting"
    put_label(out, f"segment {seg}  {state}  t={truth.t_s:6.2f}s", (8, 22), 0.6)
    if rep is not None and rep.message:
        put_label(out, rep.message[:70], (8, 46), 0.45, (0, 200, 255))
    return out


def write_report(res: DemoResult, out: Path) -> list[Path]:
    """Plots, messages.txt, the pose CSVs and, last, summary.json (atomically: a reader sees
    the whole file or none) into ``out``, which should be the run's own folder (``torchseam
    demo`` makes a new one with :func:`~torchseam.core.report.prepare_out_dir`); a ``RUNNING``
    marker there (:data:`~torchseam.core.report.RUN_MARKER`) is removed once summary.json is
    written. Returns the files written.

    Raises:
        ReportError: a file could not be written (a full disk, a permission): the message
            names the file and the error. summary.json is then not written (the marker
            stays).
    """
    from torchseam.live.plots import quaternion_plot, seam_3d_plot, series_plot

    with report_file(out):
        out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    fr = res.frames
    # segment boundaries and the arc-off approach marked on every per-frame plot
    segs, arc = [f.seg for f in fr], [f.arc_on for f in fr]
    err_uv = np.array([f.uv - f.uv_true for f in fr]).reshape(-1, 2)  # none: a search failed
    with report_file(out / "uv_error.png") as path:
        files.append(series_plot({"u error": err_uv[:, 0], "v error": err_uv[:, 1]}, "px",
                                 path, segments=segs, arc_on=arc))
    err_p = np.array([f.p - f.p_true for f in fr]).reshape(-1, 3)
    with report_file(out / "xyz_error.png") as path:
        files.append(series_plot({"x": err_p[:, 0], "y": err_p[:, 1], "z": err_p[:, 2]},
                                 "located 3D error (mm)", path, segments=segs, arc_on=arc))
    with report_file(out / "torch_error.png") as path:
        files.append(series_plot(
            {"torch to true seam": np.array([f.torch_err_mm for f in fr])}, "mm", path,
            segments=segs, arc_on=arc))
    # a command's time is its frame's: the poses sent with the arc off are the approach
    arc_at = {(f.seg, round(f.t_s, 6)): f.arc_on for f in fr}
    names = list(res.quats)
    appr = {n: np.array([not arc_at.get((s, round(t, 6)), True)
                         for s, _p, _q, _seen, t in res.sent if s == n], bool) for n in names}
    if res.quats:  # (none: no segment started, e.g. a start pose the gate refused)
        with report_file(out / "quaternions.png") as path:
            files.append(quaternion_plot(list(res.quats.items()), path, approach=appr))
    paths = {k: v for k, v in res.paths.items() if v}
    tracked = paths.get("tracked", [])
    approach = ({"tracked": [appr[n] for n in names]}
                if len(tracked) == len(names)
                and all(len(a) == len(p) for a, p in zip(appr.values(), tracked, strict=True))
                else None)
    with report_file(out / "seam_3d.png") as path:
        files.append(seam_3d_plot(paths, path,
                                  segment_names=names if len(tracked) == len(names) else None,
                                  approach=approach))
    with report_file(out / "messages.txt") as path:
        path.write_text("\n".join(res.messages) + "\n")
        files.append(path)
    files += write_poses_csv(res, out / "poses.csv")
    # last: what the run was and how it ended; until it is there, RUNNING says it is not
    files.append(write_json_atomic(out / "summary.json", res.summary))
    with report_file(out / RUN_MARKER) as path:
        path.unlink(missing_ok=True)
    return files


def write_poses_csv(res: DemoResult, path: Path) -> list[Path]:
    """Every pose the link accepted, in order, in the pose CSV that ``torchseam robot check``
    reads (:func:`~torchseam.core.poses_csv.write_pose_csv`): ``t,x,y,z,q1,q2,q3,q4``, the
    command time s on the simulation clock plus ``TRANSFER_S`` for each change of segment
    before it, the torch TCP in the robot base (mm, quaternion w, x, y, z). The positioner
    turns the part between segments, so ``robot check``'s clearance test with the part as
    configured fits segment a only: per segment, ``poses_<s>.csv`` and ``part_<s>.yaml`` (the
    part as turned for it) check each (``robot check poses_b.csv --part part_b.yaml``)."""
    import dataclasses as dc

    from torchseam.core.config import Pose, save_config
    from torchseam.core.poses_csv import write_pose_csv
    from torchseam.core.transforms import matrix_to_quat

    segs = list(dict.fromkeys(seg for seg, *_ in res.sent))
    t = np.array([c[4] + TRANSFER_S * segs.index(c[0]) for c in res.sent])
    P = np.array([c[1] for c in res.sent]).reshape(-1, 3)
    Q = np.array([c[2] for c in res.sent]).reshape(-1, 4)
    with report_file(path):
        files = [write_pose_csv(path, P, Q, t)]
    for name in segs:
        rows = [c for c in res.sent if c[0] == name]
        with report_file(path.with_name(f"poses_{name}.csv")) as seg_path:
            files.append(write_pose_csv(seg_path,
                                        np.array([c[1] for c in rows]),
                                        np.array([c[2] for c in rows]),
                                        np.array([c[4] for c in rows])))
        T = res.part_poses.get(name)
        if res.part is not None and T is not None:
            q = matrix_to_quat(T[:3, :3])
            turned = dc.replace(res.part, placement=Pose(
                tuple(float(v) for v in T[:3, 3]),
                tuple(float(v) for v in q / np.linalg.norm(q))))
            with report_file(path.with_name(f"part_{name}.yaml")) as part_path:
                save_config(turned, part_path)
            files.append(part_path)
    return files
