"""``torchseam weld``: weld a real cell (or the virtual one) through its real interfaces.

The weld process gets what a real cell gives: frames with their exposure time on the camera's
clock (:class:`~torchseam.live.framestream.StreamCamera`) and the controller's EGM datagrams
(:class:`~torchseam.robot.egm.EgmLink`, pose mode) with the fed-back pose, the controller's time
and RAPID's data (:mod:`torchseam.robot.egm.rapid_data`). It gives back what a real cell takes:
torch poses over EGM and, in the same replies, the arc request and the segment's state.

Per segment, RAPID brings the torch to the segment's start and hands over to EGM (phase
GUIDED); the weld tracks, guides and asks for the arc; when the torch reached the segment's
end it says DONE (or ABORT with the reason) and RAPID takes back.

**The pose of a frame** is the controller's fed-back pose interpolated at the frame's exposure
time (:mod:`torchseam.live.clocks`): the camera's clock is brought onto the PC's by an offset
estimated online with the camera's latency from the cell file, the controller's clock the same
way with one EGM cycle. A frame with no fed-back pose on both sides of its exposure time gives
no measurement (counted, never guessed).

**It never claims more than it did**: a camera that stops delivering for ``stall_frames``
frame periods holds the robot where it is and puts the arc out at once; a segment RAPID takes
back before its end (EGM's timeout, RAPID's own), a segment the loop could not finish, a
signal: each is reported with its reason and the exit code says the weld is incomplete.
SIGINT / SIGTERM: the arc out, the robot held, the segment aborted towards RAPID, the report
marked ``interrupted`` (exit 130 / 143).
"""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchseam.core.errors import TorchseamError
from torchseam.core.transforms import invert, pose_matrix
from torchseam.live.cellfile import WeldCell
from torchseam.live.clocks import ClockOffset, PoseHistory
from torchseam.live.events import DemoControl, FrameRecord
from torchseam.live.loop import LiveLoop, StepReport, egm_config_for
from torchseam.live.parts import LiveParts
from torchseam.live.runner import MAX_GAP_MM as MAX_GAP_MM  # (re-exported)
from torchseam.live.runner import (
    MOVING_FRACTION,
    MOVING_WINDOW_S,
    REPLY_MOVING_WINDOW_S,
    STANDING_MM_S,
    ArcGapMeter,
    CellFrame,
    SegmentJob,
    run_segment,
)
from torchseam.robot.egm import rapid_data as rd
from torchseam.vision.exposure import ExposureController, frame_stats

#: exit codes of ``torchseam weld``
EXIT_OK, EXIT_INCOMPLETE, EXIT_BAD_INPUT, EXIT_SIGINT, EXIT_SIGTERM = 0, 1, 2, 130, 143
#: the older schema: how long the weld holds the torch at a segment's end for RAPID's EGM to
#: converge and take back (RAPID's convergence condition: the torch still for about a second)
CONVERGE_WAIT_S = 2.5


@dataclass
class ControllerView:
    """What the weld knows of the controller, kept up to date by the EGM link's thread.

    Attributes:
        offset: the controller's clock against the PC's.
        poses: fed-back torch poses on the PC's clock.
        rapid: RAPID's newest data (None: none yet, or a controller on the older schema).
        motions: guided motions RAPID has started (a new one each time the phase becomes
            GUIDED): the link starts a new session on each.
        datagrams: EgmRobot accepted; ``without_rapid``: of them without RAPID data.
    """

    cycle_s: float
    delay_s: float = 0.0
    offset: ClockOffset = field(init=False)
    poses: PoseHistory = field(init=False)
    rapid: rd.RapidData | None = None
    motions: int = 0
    datagrams: int = 0
    without_rapid: int = 0
    gap: ArcGapMeter = field(default_factory=ArcGapMeter)
    # the older schema: the weld decides that a guided motion started (the robot stands at a
    # segment's start); the next datagram then starts a new session of the link
    new_motion_pending: bool = False
    arc_now: Any = None          # () -> bool: the arc request the replies carry now
    # the newest fed-back torch positions (t PC s, p (3,)): the torch's speed now
    recent: deque[tuple[float, np.ndarray]] = field(default_factory=lambda: deque(maxlen=64))
    _resets: int = 0

    def __post_init__(self) -> None:
        # 2nd percentile: a cycle that ran late stamps a pose that leaves early (a shorter
        # delay than the controller's least): a few of those must not move the offset
        self.offset = ClockOffset(known_delay_s=self.delay_s, window=1000, quantile=0.02)
        # a few lost datagrams in a row leave a gap the smooth motion spans; a longer one (the
        # controller silent) leaves the frames in it without a pose
        self.poses = PoseHistory(maxlen=5000, max_gap_s=max(0.05, 12 * self.cycle_s))

    def on_robot(self, robot: Any, at: float) -> bool:
        """The link's hook: one accepted ``EgmRobot`` arrived at ``at`` (PC clock)."""
        self.datagrams += 1
        fb = robot.feedBack
        t_fb = fb.time.sec + fb.time.usec * 1e-6
        self.offset.add(t_fb, at)
        if self.offset.resets != self._resets:   # the controller's clock jumped
            self._resets = self.offset.resets
            self.poses.clear()
        c = fb.cartesian
        q = np.array([c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3])
        n = float(np.linalg.norm(q))
        if n > 0:
            p = np.array([c.pos.x, c.pos.y, c.pos.z])
            self.poses.add(self.offset.to_pc(t_fb), pose_matrix(p, q / n))
            self.recent.append((self.offset.to_pc(t_fb), p))
            self.gap.add(p, bool(self.arc_now()) if self.arc_now is not None else False)
        data = rd.read_rapid_data(robot)
        if data is None:
            self.without_rapid += 1
        prev, self.rapid = self.rapid, data
        new = (data is not None and data.phase == rd.RapidPhase.GUIDED
               and (prev is None or prev.phase != rd.RapidPhase.GUIDED
                    or prev.segment != data.segment))
        if self.new_motion_pending:
            self.new_motion_pending, new = False, True
        if new:
            self.motions += 1
        return new

    def speed_mm_s(self, window_s: float) -> float:
        """The torch's speed over the newest ``window_s`` of fed-back poses (mm/s; 0 with
        fewer than two poses in it)."""
        recent = tuple(self.recent)   # (one C call: the link's thread appends meanwhile)
        if len(recent) < 2:
            return 0.0
        t1, p1 = recent[-1]
        old = [(t, p) for t, p in recent if t >= t1 - window_s - 1e-9]
        t0, p0 = old[0]
        return float(np.linalg.norm(p1 - p0)) / (t1 - t0) if t1 > t0 else 0.0


@dataclass
class SensorReply:
    """What the weld says to RAPID in every reply (the link's thread writes it).

    The arc request is a lease: the weld's loop renews it with every frame it handles, and a
    request older than ``lease_s`` goes out as False. A weld whose loop stalls (starved of the
    CPU, stuck) while the link's thread still answers does not keep the arc burning over a
    torch the link is holding still."""

    arc_request: bool = False
    segment: int = 0
    state: rd.SensorState = rd.SensorState.WAIT
    heartbeat: int = 0
    lease_s: float = 0.06
    moving: Any = None          # () -> bool: the torch moves now (None: not checked)
    _since: float = 0.0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def set(self, arc_request: bool, segment: int, state: rd.SensorState) -> None:
        with self._lock:
            self.arc_request, self.segment, self.state = arc_request, segment, state
            self._since = time.monotonic()

    def effective(self) -> bool:
        """The arc request the next reply carries: False once the lease ran out, and False
        while the fed-back torch stands (checked every cycle: a loop that falls behind leaves
        the robot standing at its last target between two frames; the arc must not burn
        there)."""
        return (self.arc_request and time.monotonic() - self._since <= self.lease_s
                and (self.moving is None or bool(self.moving())))

    def on_reply(self, msg: Any) -> None:
        with self._lock:
            self.heartbeat = rd.next_heartbeat(self.heartbeat)
            arc = self.effective()
            rd.write_sensor_data(msg, rd.SensorData(arc, self.segment, self.state,
                                                    self.heartbeat))


@dataclass
class SegmentOutcome:
    name: str
    welded: bool
    reason: str
    travelled_mm: float = 0.0
    unwelded_mm: float = 0.0
    frames: int = 0


@dataclass
class WeldResult:
    segments: list[SegmentOutcome] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)
    frames: int = 0
    frames_no_pose: int = 0
    frames_dropped: int = 0
    stalls: int = 0
    holds: Counter[str] = field(default_factory=Counter)
    latency_ms: list[float] = field(default_factory=list)
    interrupted: str = ""
    # every pose the link accepted: (segment, t PC s, p (3,), q (4,))
    poses: list[tuple[str, float, np.ndarray, np.ndarray]] = field(default_factory=list)
    link: dict[str, Any] = field(default_factory=dict)
    clocks: dict[str, Any] = field(default_factory=dict)
    # the automatic exposure (camera.auto_exposure): (segment, frame t PC s, the scale asked
    # for after that frame, for the frames the camera exposes from its arrival on)
    exposure: list[tuple[str, float, float]] = field(default_factory=list)


class Interrupted(Exception):
    """SIGINT / SIGTERM arrived."""


class WeldRunner:
    """One weld: the cell's interfaces, the weld plan, the live loop per segment.

    Args:
        cell: the cell file (calibration, camera, controller).
        plan_report: the pre-flight of the part (passed).
        parts: the live stack's settings.
        segments: the segment letters to weld.
        length_mm: weld only this much of each segment (None: all of it).
        tracker: the tracker name (default the live tracker).
        progress: ``progress(text)`` for the terminal.
        observer: called with a :class:`~torchseam.live.events.DemoEvent` per frame (the
            console; the record's truth fields are NaN: a cell has no truth).
        control: the operator's hold / resume / stop (:class:`~torchseam.live.events.DemoControl`):
            a hold holds the robot where it stands with the arc out until resumed; a stop
            aborts the segment towards RAPID and ends the weld.
    """

    def __init__(self, cell: WeldCell, plan_report: Any, parts: LiveParts, segments: str,
                 length_mm: float | None, tracker: str = "anchored",
                 model_path: Any = None, progress: Any = print,
                 connect_timeout_s: float = 60.0, wait_rapid_s: float = 60.0,
                 observer: Any = None, control: DemoControl | None = None) -> None:
        self.cell, self.report, self.parts = cell, plan_report, parts
        self.calib = cell.calibration
        self.segments, self.length_mm = segments, length_mm
        self.tracker, self.model_path = tracker, model_path
        self._fps_said = False
        self.observer, self.control = observer, control
        self.progress = progress
        self.connect_timeout_s, self.wait_rapid_s = connect_timeout_s, wait_rapid_s
        self.res = WeldResult()
        self.view = ControllerView(cycle_s=cell.controller.cycle_ms / 1e3,
                                   delay_s=cell.controller.feedback_delay_ms / 1e3)
        self.period_s = 1.0 / cell.calibration.process.frame_rate_hz
        self.reply = SensorReply(lease_s=2.5 * self.period_s)
        self.view.arc_now = self.reply.effective
        self.reply.moving = lambda: self.view.speed_mm_s(REPLY_MOVING_WINDOW_S) >= STANDING_MM_S
        self.tool_inv = invert(self.calib.tool.matrix())
        self.period_s = 1.0 / self.calib.process.frame_rate_hz
        self.stall_s = cell.camera.stall_frames * self.period_s
        self.cam_offset = ClockOffset(known_delay_s=cell.camera.latency_ms / 1e3, window=250)
        self._signal = 0
        self.cam: Any = None      # the StreamCamera, once open
        self._partial: SegmentOutcome | None = None   # the segment a signal interrupted
        self.old_schema = False   # the controller's EGM carries no RAPID data
        self._raise_on_signal = False   # True while blocked in set-up (no loop checks a flag)
        self.ae: ExposureController | None = None
        if cell.camera.auto_exposure:
            if parts.exposure is None:
                raise TorchseamError("camera.auto_exposure is set, but no exposure settings "
                                     "were read (configs/exposure.yaml)")
            self.ae = ExposureController(parts.exposure)

    # ------------------------------------------------------------------ set-up

    def _egm_config(self) -> Any:
        parts, proc = self.parts, self.calib.process
        egm = egm_config_for(parts.egm, parts.live, proc.frame_rate_hz)
        safety = dataclasses.replace(egm.safety,
                                     max_step_mm=max(egm.safety.max_step_mm, 1.25 * proc.step_mm))
        c = self.cell.controller
        net = dataclasses.replace(egm.network, host=c.host, port=c.port,
                                  controller_host=c.controller_host,
                                  controller_port=c.controller_port)
        return dataclasses.replace(egm, mode="pose", safety=safety, network=net)

    def on_signal(self, signum: int, _frame: Any) -> None:
        self._signal = signum
        if self._raise_on_signal:   # blocked in a connect or a compile: leave it now
            raise Interrupted(signal.Signals(signum).name)

    def check_signal(self) -> None:
        """Raise :class:`Interrupted` once SIGINT / SIGTERM came (loops that wait call it)."""
        if self._signal:
            raise Interrupted(signal.Signals(self._signal).name)

    # ------------------------------------------------------------------ the run

    def open(self) -> None:
        """Listen for the controller, connect to the camera, wait for the controller's first
        datagrams (and RAPID's data with them)."""
        from torchseam.robot.egm import EgmLink

        cfg = self._egm_config()
        self.link = EgmLink(cfg, on_robot=self.view.on_robot, on_reply=self.reply.on_reply)
        self.link.start()
        self.progress(f"weld: EGM listening on {cfg.network.host}:{cfg.network.port} for the "
                      f"controller at {cfg.network.controller_host}:"
                      f"{cfg.network.controller_port}; camera {self.cell.camera.source}")
        from torchseam.live.cameras import open_camera

        cam = self.calib.camera
        self.cam = open_camera(self.cell.camera.source, (cam.width, cam.height),
                               self.calib.process.frame_rate_hz, self.connect_timeout_s,
                               self.cell.camera.exposure_us,
                               say=lambda m: self.progress("weld: " + m))
        if self.cam.exposure_us is not None:
            self.progress(f"weld: the camera's exposure time set to {self.cam.exposure_us:g} us")
        if self.ae is not None:
            self.cam.request_exposure(self.ae.scale)   # one it cannot take: refused here
            c = self.ae.cfg
            self.progress(f"weld: automatic exposure on: {c.min_scale:g} .. {c.max_scale:g} x "
                          "the camera's exposure, from the window round the tracked point "
                          "(configs/exposure.yaml)")
        self._wait_controller()

    def warm(self) -> None:
        """Compile (or load from numba's cache) TIPM's kernels now, on a blank frame of the
        camera's size: not while EGM guides."""
        cam = self.calib.camera
        self.parts.tipm(np.zeros((cam.height, cam.width, 3), np.uint8))

    def close(self) -> None:
        """Arc off towards RAPID, the figures kept, the camera and the link closed."""
        self.reply.set(False, self.reply.segment, self.reply.state)
        time.sleep(0.05)           # the arc-off reaches the controller
        self.res.link = _link_figures(self.link)
        self.res.clocks = {
            "controller_offset_s": self.view.offset.offset_s,
            "controller_clock_resets": self.view.offset.resets,
            "camera_offset_s": self.cam_offset.offset_s,
            "camera_latency_ms": self.cell.camera.latency_ms}
        if self.cam is not None:
            self.res.frames_dropped += self.cam.dropped
            self.cam.close()
        self.link.stop()

    def run(self) -> WeldResult:
        """Weld the asked segments (see the module docstring)."""
        try:
            self._raise_on_signal = True
            self.warm()
            self.open()
            self._raise_on_signal = False
            todo = [s for s in self.report.plan.segments if s.name in self.segments]
            for seg in todo:
                self.check_signal()
                self.res.segments.append(self._segment(seg))
        except Interrupted as e:
            self._raise_on_signal = False
            self.res.interrupted = str(e)
            if self._partial is not None:
                self.res.segments.append(self._partial)
            self._abort_current("interrupted by " + str(e))
        except Exception as e:
            # a fault of this program: arc out, the segment aborted towards RAPID, the robot
            # held; the caller reports it
            self._raise_on_signal = False
            self._abort_current(f"internal error: {type(e).__name__}: {e}")
            raise
        finally:
            if hasattr(self, "link"):
                self.close()
        return self.res

    def _abort_current(self, why: str) -> None:
        """Tell RAPID the segment in hand is aborted, arc off, robot held where it stands."""
        if why:
            self.res.messages.append(why)
        if not hasattr(self, "link"):
            return          # interrupted before the link was open: nothing to tell
        self.reply.set(False, self.reply.segment, rd.SensorState.ABORT
                       if self.reply.segment else rd.SensorState.WAIT)
        self._hold_here()
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:     # RAPID takes back (or the controller is gone)
            r = self.view.rapid
            if r is None or r.phase != rd.RapidPhase.GUIDED:
                break
            time.sleep(0.01)

    def _wait_controller(self) -> None:
        """Until the controller's datagrams arrive; says whether RAPID's data comes with them."""
        deadline = time.monotonic() + self.connect_timeout_s
        while self.view.datagrams < 5:
            self.check_signal()
            if time.monotonic() > deadline:
                raise TorchseamError(
                    f"no EGM datagram from the controller at {self.cell.controller.controller_host}"
                    f":{self.cell.controller.controller_port} within "
                    f"{self.connect_timeout_s:g} s (is RAPID's EGM set up towards "
                    f"{self.cell.controller.host}:{self.cell.controller.port}?)")
            time.sleep(0.02)
        self.old_schema = self.view.rapid is None
        if self.old_schema:
            msg = ("the controller's EGM is of the older schema (no RAPIDfromRobot: RobotWare "
                   "before 6.10): the arc and the segment sequence stay with RAPID; this weld "
                   "guides each segment from when the robot stands at its programmed start "
                   "and holds the torch at its end (RAPID takes back when EGM converged); "
                   "what was welded is RAPID's to say")
            self.res.messages.append(msg)
            self.progress("weld: " + msg)
        self.progress(f"weld: controller connected (clock offset "
                      f"{self.view.offset.offset_s:+.3f} s to this PC), RAPID data channel "
                      + ("off" if self.old_schema else "on"))

    def _wait_guided(self, number: int, name: str) -> str:
        """Wait until RAPID hands segment ``number`` over to EGM; '' or why it did not."""
        deadline = time.monotonic() + self.wait_rapid_s
        self.reply.set(False, 0, rd.SensorState.WAIT)
        if self.old_schema:
            return self._wait_at_start(number, name, deadline)
        while True:
            self.check_signal()
            r = self.view.rapid
            if r is not None and r.phase == rd.RapidPhase.GUIDED and r.segment == number:
                return ""
            if r is not None and r.phase == rd.RapidPhase.ENDED:
                return "RAPID's program ended before the segment"
            if r is not None and r.phase == rd.RapidPhase.GUIDED and r.segment != number:
                # RAPID runs a segment this weld was not asked to weld: say no to it
                self.reply.set(False, r.segment, rd.SensorState.ABORT)
            if time.monotonic() > deadline:
                return f"RAPID did not hand segment {name} over within {self.wait_rapid_s:g} s"
            time.sleep(0.005)

    def _wait_at_start(self, number: int, name: str, deadline: float) -> str:
        """The older schema: until the robot stands (0.2 s) within 2 mm and 2 degrees of the
        segment's programmed start; then a new session of the link on it."""
        seg = next(s for s in self.report.plan.segments if s.index + 1 == number)
        geo = self.report.plan.geometry(seg)
        s0 = float(geo.s_at(np.array([seg.phi_start]))[0])
        approach = self.calib.process.look_ahead_mm + self.parts.plan.approach_mm
        T0 = self.report.plan.nominal_tcp(seg, np.array([s0 - approach]))[0]
        while True:
            self.check_signal()
            newest = self.view.poses.newest
            if newest is not None:
                t, T = newest
                T_old = self.view.poses.nearest(t - 0.2, 0.03)
                near = (np.linalg.norm(T[:3, 3] - T0[:3, 3]) < 2.0 and np.degrees(np.arccos(
                    np.clip((np.trace(T[:3, :3].T @ T0[:3, :3]) - 1) / 2, -1, 1))) < 2.0)
                still = T_old is not None and np.linalg.norm(T[:3, 3] - T_old[:3, 3]) < 0.05
                if near and still:
                    self.view.new_motion_pending = True
                    time.sleep(0.05)
                    return ""
            if time.monotonic() > deadline:
                return (f"the robot did not stand at segment {name}'s programmed start within "
                        f"{self.wait_rapid_s:g} s")
            time.sleep(0.01)

    def _guided(self, number: int) -> str:
        """'' while RAPID lets the weld guide segment ``number``, else what RAPID says (its
        phase). The older schema: always '' (RAPID takes back by EGM's convergence, when the
        weld holds the torch at the end)."""
        if self.old_schema:
            return ""
        r = self.view.rapid
        if r is None:
            return "no data"
        if r.phase != rd.RapidPhase.GUIDED or r.segment != number:
            return r.phase.name
        return ""

    def _segment(self, seg: Any) -> SegmentOutcome:
        from torchseam.robot.reach import ReachGate
        from torchseam.track.peers import make_tracker

        number = seg.index + 1
        # everything the segment needs is built (and its kernels warm) before RAPID hands
        # over: once EGM guides, the link must answer every 4 ms and EGM's timeout runs
        geo = segment_geometry(self.report.plan, seg, self.calib, self.parts.plan,
                               self.length_mm)
        gate = ReachGate(self.parts.robot, cell=self.calib, part=self.report.plan.part,
                         part_pose_mm=geo.part_pose)
        tipm = self.parts.tipm
        # the part's joint decides what is tracked (a fillet: the tracker; else its profile)
        joint = self.report.plan.part.joint
        trk = (make_tracker(self.tracker, tipm, model_path=self.model_path) if joint == "fillet"
               else self.parts.tracker(self.tracker, joint, self.model_path))
        fps = self.calib.process.frame_rate_hz
        if trk.fitted_fps and abs(trk.fitted_fps - fps) > 1e-3 * fps and not self._fps_said:
            self._fps_said = True   # said once, and kept in the report's messages
            self.res.messages.append(
                f"the camera runs at {fps:g} frames/s, the tracker's model was fitted at "
                f"{trk.fitted_fps:g}: its motion per frame is the fit's (fit one at this rate "
                "for the best accuracy)")
            self.progress(f"weld: note: {self.res.messages[-1]}")
        loop = LiveLoop(self.calib, trk, self.link,
                        self.report.plan.plan_config(seg, self.parts.plan), self.parts.live,
                        tipm, self.parts.ecal, nominal=geo.nominal)
        why = self._wait_guided(number, seg.name)
        if why:
            self.progress(f"weld: segment {seg.name}: {why}")
            return SegmentOutcome(seg.name, False, why)
        self.link.gate = gate
        self.reply.set(False, number, rd.SensorState.TRACKING)
        self.progress(f"weld: segment {seg.name}: EGM guides ({geo.length_mm:.1f} mm after a "
                      f"{geo.approach_mm:.0f} mm approach)")
        job = SegmentJob(seg.name, geo.approach_mm, geo.length_mm,
                         self.calib.process.weld_speed_mm_s * self.period_s, self.period_s,
                         self.tool_inv)
        cell = _CellInterfaces(self, number, seg.name, geo.length_mm, geo.approach_mm)
        out = SegmentOutcome(seg.name, False, "")
        try:
            run = run_segment(cell, loop, job, control=self.control, observer=self.observer,
                              link=self.link, messages=self.res.messages)
            out.frames = run.frames
            gap_why = "" if self.old_schema else self.view.gap.reason()
            # (the older schema: the arc is RAPID's, the weld guided to the end)
            out.welded = run.reached_end and not gap_why
            out.reason = "; ".join(w for w in (gap_why, run.reason) if w)
            out.travelled_mm = max(0.0, run.travelled_mm - geo.approach_mm)
        except Interrupted as e:
            out.travelled_mm = max(0.0, cell.along_mm - geo.approach_mm)
            out.reason = (f"interrupted by {e} after {out.travelled_mm:.1f} of "
                          f"{geo.length_mm:.1f} mm")
            self._partial = out
            raise
        finally:
            out.unwelded_mm = float("nan") if self.old_schema else self.view.gap.gap_mm
            self.res.latency_ms += list(loop.stats.timings_ms.get("frame->command", []))
            for k, n in loop.stats.hold_reasons.items():
                self.res.holds[k] += n
            loop.finish()
        state = rd.SensorState.DONE if out.welded else rd.SensorState.ABORT
        self.reply.set(False, number, state)
        self._hold_here()
        if self.old_schema:
            # no word from RAPID: hold the torch until EGM has converged and RAPID took back
            end = time.monotonic() + CONVERGE_WAIT_S
            while time.monotonic() < end and not self._signal:
                time.sleep(0.02)
        else:
            self._wait_taken_back(number)
        self.progress(f"weld: segment {seg.name}: " + (
            f"welded ({out.travelled_mm:.1f} mm)" if out.welded else f"NOT welded: {out.reason}"))
        return out

    def _moving(self) -> bool:
        """The torch moved at least :data:`~torchseam.live.runner.MOVING_FRACTION` of the weld
        speed over the last :data:`~torchseam.live.runner.MOVING_WINDOW_S` (the arc is never
        asked for over a torch that stands: it would burn through)."""
        v = self.view.speed_mm_s(MOVING_WINDOW_S)
        return v >= MOVING_FRACTION * self.calib.process.weld_speed_mm_s

    def _hold_here(self) -> None:
        """Hold the robot where it stands: its fed-back pose as the target (the link checks
        it like any), else the link's own hold on the last pose it sent."""
        newest = self.view.poses.newest
        ok = False
        if newest is not None:
            _, T = newest
            from torchseam.core.transforms import matrix_to_quat

            ok = bool(self.link.set_target(T[:3, 3], matrix_to_quat(T[:3, :3]),
                                           measured_at=time.monotonic()).ok)
        if not ok:
            self.link.clear_measurement()

    def _wait_taken_back(self, number: int, timeout_s: float = 3.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            r = self.view.rapid
            if r is None or r.phase != rd.RapidPhase.GUIDED or r.segment != number:
                return
            time.sleep(0.01)


class _CellInterfaces:
    """The cell through its interfaces, for :func:`~torchseam.live.runner.run_segment`: the
    camera's frames with their exposure time brought onto this PC's clock, the fed-back pose
    interpolated there, the arc request and the segment's state in the link's replies, RAPID
    taking the segment back."""

    def __init__(self, w: WeldRunner, number: int, name: str, length_mm: float,
                 approach_mm: float) -> None:
        self.w, self.number, self.name = w, number, name
        self.length_mm, self.approach_mm = length_mm, approach_mm
        self.gap = w.view.gap
        self.t_handover = self.last_print = time.monotonic()
        self.stalled_since: float | None = None
        self.motions = w.view.motions
        self.along_mm = 0.0

    def next_frame(self) -> CellFrame | str | None:
        w = self.w
        f = w.cam.get(w.stall_s)
        now = time.monotonic()
        if f is None:
            if w.cam.error:
                return str(w.cam.error)
            if self.stalled_since is None:
                self.stalled_since = now
                w.res.stalls += 1
                self.set_arc(False)
                w._hold_here()
                w.res.messages.append(f"segment {self.name}: no frame for "
                                      f"{w.stall_s * 1e3:.0f} ms: arc off, robot held")
                w.progress(w.res.messages[-1])
            elif (now - self.stalled_since) * 1e3 > 5 * w.parts.live.max_blind_ms:
                return f"the camera delivered no frame for {now - self.stalled_since:.1f} s"
            return None
        w.cam_offset.add(f.t_exp_s, f.t_arrival_s)
        t_exp = w.cam_offset.to_pc(f.t_exp_s)
        T_B_W = w.view.poses.at(t_exp)
        w.res.frames += 1
        if T_B_W is None:
            w.res.frames_no_pose += 1
            return None
        if self.stalled_since is not None:
            w.res.messages.append(f"segment {self.name}: frames back after "
                                  f"{now - self.stalled_since:.2f} s")
            self.stalled_since = None
        if t_exp < self.t_handover + w.period_s:
            return None     # exposed before RAPID handed over: the robot may not stand yet
        return CellFrame(f.image, t_exp, T_B_W)

    def torch_now(self) -> np.ndarray | None:
        newest = self.w.view.poses.newest
        return None if newest is None else newest[1][:3, 3]

    def moving(self) -> bool:
        return self.w._moving()

    def set_arc(self, on: bool) -> None:
        self.w.reply.set(on, self.number, rd.SensorState.TRACKING)

    def hold_here(self) -> None:
        self.w._hold_here()

    def guided(self) -> str:
        w = self.w
        w.check_signal()
        phase = w._guided(self.number)
        if phase:
            return (f"RAPID took the segment back ({phase}) after "
                    f"{max(0.0, self.along_mm - self.approach_mm):.1f} of "
                    f"{self.length_mm:.1f} mm")
        if w.view.motions != self.motions:     # EGM restarted: the robot stood still
            self.motions = w.view.motions
            w.res.messages.append(f"segment {self.name}: EGM restarted by the controller; "
                                  "going on from where the robot is")
        return ""

    def label(self, t_s: float | None = None) -> str:
        return f"segment {self.name}:"

    def record(self, f: CellFrame, rep: StepReport | None, arc: bool,
               along_mm: float) -> FrameRecord:
        """No truth in a cell: NaN where the demo has it."""
        from torchseam.track.fusion import TrackStatus

        w = self.w
        self.along_mm = along_mm
        if rep is not None and rep.command is not None and rep.command.ok:
            c = rep.command
            w.res.poses.append((self.name, c.t_s, c.p.copy(), c.q.copy()))
        now = time.monotonic()
        if now - self.last_print > 2.0:
            self.last_print = now
            w.progress(f"weld: segment {self.name}: "
                       f"{max(0.0, along_mm - self.approach_mm):5.1f} / "
                       f"{self.length_mm:.1f} mm, {rep.state.value if rep else 'start'}")
        loc = rep.location if rep is not None else None
        if w.ae is not None and f.image is not None:
            scale = auto_exposure_step(w.ae, w.cam, f.image, loc.uv if loc is not None else None)
            w.res.exposure.append((self.name, f.t_s, scale))
        nan2, nan3 = np.full(2, np.nan), np.full(3, np.nan)
        return FrameRecord(self.name, f.t_s, arc,
                           loc.uv if loc is not None else nan2, nan2,
                           int(loc.status) if loc is not None else int(TrackStatus.LOST),
                           rep.state.value if rep is not None else "start",
                           loc.p if loc is not None else nan3, nan3, float("nan"), "")


@dataclass(frozen=True)
class SegmentJobGeometry:
    """Where a segment runs on the design part: the part's pose (turned for it), the
    programmed path (positions, (N, 3) base mm, from the programmed start), the approach and
    the length to weld."""

    part_pose: np.ndarray
    nominal: np.ndarray
    approach_mm: float
    length_mm: float


def segment_geometry(plan: Any, seg: Any, cell: Any, plan_cfg: Any,
                     length_mm: float | None) -> SegmentJobGeometry:
    """The :class:`SegmentJobGeometry` of ``seg`` of ``plan`` (the demo's, from the design)."""
    geo = plan.geometry(seg)
    s0 = float(geo.s_at(np.array([seg.phi_start]))[0])
    seg_len = (float(geo.s_at(np.array([seg.phi_end]))[0]) - s0) % geo.seam_length_mm
    if length_mm is not None:
        seg_len = min(seg_len, length_mm)
    approach = cell.process.look_ahead_mm + plan_cfg.approach_mm
    nominal = geo.nominal_tcp(s0 - approach + np.arange(0.0, approach + seg_len + 10.0, 0.5))
    return SegmentJobGeometry(geo.T_B_Tnom, nominal[:, :3, 3], approach, seg_len)


def _link_figures(link: Any) -> dict[str, Any]:
    st = link.stats
    lat = np.array(list(st.latency_ms)) if len(st.latency_ms) else np.zeros(0)
    return {"received": st.received, "sent": st.sent, "late_replies": st.late_replies,
            "reply_p50_ms": float(np.percentile(lat, 50)) if len(lat) else None,
            "reply_p99_ms": float(np.percentile(lat, 99)) if len(lat) else None,
            "refused": dict(st.refused), "dropped": dict(st.dropped),
            "sessions": st.sessions, "watchdog_trips": st.watchdog_trips}


def auto_exposure_step(ae: ExposureController, cam: Any, image: np.ndarray,
                       uv: np.ndarray | None) -> float:
    """One frame of the weld's automatic exposure: the frame's window round the tracked point
    ``uv`` (None: the whole frame) into ``ae``, and the scale it chose asked of ``cam``
    (:meth:`~torchseam.live.framestream.QueuedCamera.request_exposure`) when it changed;
    returns that scale."""
    before = ae.scale
    scale = ae.update(frame_stats(image, uv, ae.cfg))
    if scale != before:
        cam.request_exposure(scale)
    return scale


def _exposure_figures(res: WeldResult) -> dict[str, Any] | None:
    """summary.json's ``exposure``: the scales the automatic exposure asked for (None: off)."""
    if not res.exposure:
        return None
    s = np.array([x for *_, x in res.exposure])
    return {"auto": True, "scale_min": float(s.min()), "scale_median": float(np.median(s)),
            "scale_max": float(s.max()), "changes": int(np.count_nonzero(np.diff(s))),
            "file": "exposure.csv"}


def weld_summary(res: WeldResult, info: dict[str, Any]) -> dict[str, Any]:
    """summary.json of a weld (no truth columns: a real cell has none)."""
    lat = np.array(res.latency_ms)
    incomplete = [{"segment": s.name, "reason": s.reason} for s in res.segments
                  if not s.welded]
    asked = info.get("segments", "")
    done = {s.name for s in res.segments}
    incomplete += [{"segment": n, "reason": "not reached"} for n in asked if n not in done]
    return {
        **info,
        "segments_welded": [s.name for s in res.segments if s.welded],
        "segments_incomplete": incomplete,
        "travelled_mm": {s.name: round(s.travelled_mm, 3) for s in res.segments},
        "unwelded_mm": {s.name: round(s.unwelded_mm, 3) for s in res.segments},
        "frames": res.frames, "frames_without_pose": res.frames_no_pose,
        "frames_dropped_by_weld": res.frames_dropped, "camera_stalls": res.stalls,
        "holds": dict(res.holds),
        "latency_p50_ms": float(np.percentile(lat, 50)) if len(lat) else None,
        "latency_p99_ms": float(np.percentile(lat, 99)) if len(lat) else None,
        "link": res.link, "clocks": res.clocks,
        "exposure": _exposure_figures(res),
        "interrupted": res.interrupted or False,
        "messages": res.messages[-200:],
    }


def write_weld_files(res: WeldResult, out: Path) -> list[Path]:
    """``poses.csv`` (every pose the link accepted: ``t,x,y,z,q1,q2,q3,q4``, t from the weld's
    first pose, the torch tip in the base; what ``torchseam robot check`` reads), one
    ``poses_<s>.csv`` per segment, ``messages.txt``, and with the automatic exposure on
    ``exposure.csv`` (``segment,t_s,scale``: the scale asked for after each frame, t from the
    weld's first frame)."""
    from torchseam.core.poses_csv import write_pose_csv

    files = []
    if res.poses:
        t0 = res.poses[0][1]
        P = np.array([p for _, _, p, _ in res.poses])
        Q = np.array([q for _, _, _, q in res.poses])
        t = np.array([t - t0 for _, t, _, _ in res.poses])
        files.append(write_pose_csv(out / "poses.csv", P, Q, t))
        for name in dict.fromkeys(s for s, *_ in res.poses):
            k = np.array([s == name for s, *_ in res.poses])
            files.append(write_pose_csv(out / f"poses_{name}.csv", P[k], Q[k], t[k]))
    (out / "messages.txt").write_text("\n".join(res.messages) + "\n")
    files.append(out / "messages.txt")
    if res.exposure:
        t0 = res.exposure[0][1]
        rows = [f"{seg},{t - t0:.6f},{x:.6g}" for seg, t, x in res.exposure]
        (out / "exposure.csv").write_text("segment,t_s,scale\n" + "\n".join(rows) + "\n")
        files.append(out / "exposure.csv")
    return files


def exit_code(res: WeldResult) -> int:
    if res.interrupted:
        return EXIT_SIGINT if res.interrupted == "SIGINT" else EXIT_SIGTERM
    return EXIT_OK if res.segments and all(s.welded for s in res.segments) else EXIT_INCOMPLETE


__all__ = ["ControllerView", "SensorReply", "WeldRunner", "WeldResult", "weld_summary",
           "exit_code", "Path"]
