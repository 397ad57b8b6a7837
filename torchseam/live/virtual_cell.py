"""``torchseam virtual-cell``: a simulated IRC5 and laser camera in their own processes.

The weld (``torchseam weld``) gets only what a real cell gives it: frames with their exposure
time on the camera's clock over a frame stream (:mod:`torchseam.live.framestream`), and EGM
datagrams over UDP from a controller with its own clock. Nothing passes by function call.

* **The controller** (this process, :class:`VirtualController`): the simulated IRC5 on UDP at
  its EGM rate, pose mode, with its clock ``--clock-offset-s`` away from the PC's, the RAPID
  data channel (:mod:`torchseam.robot.egm.rapid_data`) and RAPID's segment sequence: for each
  segment it moves the torch to the segment's programmed start (the positioner turns the part),
  hands over to EGM (phase GUIDED), switches the arc as the sensor asks while the sensor's
  heartbeat advances, and takes back when the sensor says the segment is done (or aborts it).
  Without a valid reply for ``comm_timeout_s`` it stops the robot and the arc and ends the
  program (EGM's communication timeout); the arc goes out as soon as the sensor's data is older
  than ``arc_hold_ms``.
* **The camera** (a child process): renders what the sensor sees from the robot's actual pose
  at each exposure time (shared with the controller through a ring of poses in shared memory),
  and delivers the frame ``--camera-latency-ms`` after its exposure on a frame stream, stamped
  with the exposure time on its own clock.

The controller alone knows the truth, and when RAPID's program ends it writes
``OUT/summary.json``: the executed torch path against the true seam (the demo's keys
``seam_rmse_mm``, ``seam_max_mm``, ``axis_within_1deg``, ``poses_welded``,
``unsafe_poses_sent``) and ``arc_on_while_still_s``, ``arc_on_off_seam_s``, the unwelded length
per segment, the program's events (a communication timeout, a segment the sensor aborted).
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing as mp
import os
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torchseam.core.config import CellConfig, NoiseConfig, PartConfig
from torchseam.core.errors import TorchseamError
from torchseam.core.transforms import invert
from torchseam.live.cellfile import CameraLink, ControllerLink, WeldCell, save_weld_cell

#: the faults the virtual cell injects (``--fault``)
VIRTUAL_FAULTS = ("camera-stall", "camera-drop", "packet-loss", "controller-restart")
FAULT_S = 1.2            # a camera fault lasts this long, from the middle of each segment
RESTART_SILENCE_S = 0.5  # controller-restart: EGM silent this long, then a new sequence
OFF_SEAM_MM = 1.0        # arc on with the torch tip farther than this from the seam: off seam
STILL_MM_S = 0.5         # arc on with the torch slower than this: standing still
_REC = 22                # doubles per pose record: t, seg, arc, guided_since, T (16), 2 spare
_RING = 1024             # pose records in the shared ring


# --------------------------------------------------------------------------- the program


@dataclass
class SegmentJob:
    """One segment of RAPID's program: its number (1..6), name, the programmed start pose
    (torch TCP, base frame, the part turned for it) and the positioner's turn."""

    number: int
    name: str
    T_start: np.ndarray
    rotation_deg: float
    length_mm: float          # the segment's length to weld (``--length-mm`` or all of it)
    approach_mm: float


@dataclass
class _Cycle:
    t: float
    T: np.ndarray
    arc: bool
    seg: int


@dataclass
class ProgramLog:
    """What the controller saw: the truth the summary is computed from."""

    cycles: list[_Cycle] = field(default_factory=list)
    wire: list[tuple[float, int, bool, np.ndarray]] = field(default_factory=list)  # t, seg, arc, T
    events: list[str] = field(default_factory=list)
    outcome: dict[int, str] = field(default_factory=dict)   # segment -> done/abort/timeout
    last_reply_t: float = float("nan")
    stopped_after_timeout_s: float = float("nan")
    # per camera stall: from the first withheld frame's delivery time to the arc going out
    arc_off_after_stall_s: list[float] = field(default_factory=list)


def _shared_ring(ctx: Any) -> Any:
    return ctx.Array("d", _RING * _REC + 1, lock=False)


def write_pose(ring: Any, k: int, t: float, seg: int, arc: bool, guided_since: float,
               T: np.ndarray) -> None:
    """Record ``k`` (0, 1, ...) into the ring; the counter last, so a reader never reads a
    record before it is whole (a reader that lags a full ring behind re-reads)."""
    base = (k % _RING) * _REC
    ring[base:base + 4] = [t, float(seg), 1.0 if arc else 0.0, guided_since]
    ring[base + 4:base + 20] = list(np.asarray(T, float).reshape(-1))
    ring[_RING * _REC] = float(k + 1)


def read_poses(ring: Any, n: int = 64) -> np.ndarray:
    """The newest ``n`` records (oldest first), (m, _REC)."""
    count = int(ring[_RING * _REC])
    m = min(n, count, _RING - 1)
    out = np.empty((m, _REC))
    for i in range(m):
        k = count - m + i
        base = (k % _RING) * _REC
        out[i] = ring[base:base + _REC]
    return out


class VirtualController:
    """The simulated IRC5: EGM over UDP, RAPID's segment sequence, the arc, the truth.

    Built on :class:`~torchseam.robot.sim_controller.SimController` (the arm model, the cycle
    loop, the wire); adds the controller's own clock, the RAPID data channel and the program.
    """

    def __init__(self, cell: CellConfig, egm: Any, robot: Any, jobs: list[SegmentJob],
                 ring: Any, sensor_address: tuple[str, int], *, clock_offset_s: float,
                 comm_timeout_s: float, arc_hold_ms: float, transfer_s: float,
                 faults: tuple[str, ...], seed: int, max_segment_s: float,
                 wait_sensor_s: float, n_segments: int = 6, marks: Any = None,
                 rapid_data: bool = True) -> None:
        from torchseam.robot.egm import rapid_data as rd
        from torchseam.robot.sim_controller import SimController

        self.rd = rd
        egm = dataclasses.replace(egm, mode="pose", sim_controller=dataclasses.replace(
            egm.sim_controller, tcp_speed_mm_s=cell.process.weld_speed_mm_s))
        self.ctrl = SimController(egm, mode="pose", robot=robot, tool=cell.tool.matrix(),
                                  sensor_address=sensor_address, bind_address=("127.0.0.1", 0))
        self.tool_inv = invert(cell.tool.matrix())
        self.jobs, self.ring = jobs, ring
        self.n_segments = n_segments
        # False: a controller on the older EGM schema (RobotWare before 6.10): no RAPID data
        # either way; RAPID runs the arc itself (on after the approach, off when EGM
        # converged: the torch stood still) and takes back when EGM converged
        self.rapid_data = rapid_data
        self._path_mm = 0.0              # the torch's path since the hand-over (old schema)
        self._still_since = float("nan")
        self._T_prev: np.ndarray | None = None
        self.marks = marks              # shared with the camera: [stall start (delivery time)]
        self._stall_seen = float("nan")
        self.offset = float(clock_offset_s)
        self.comm_timeout_s = comm_timeout_s
        self.arc_hold_s = arc_hold_ms / 1e3
        self.transfer_s = transfer_s
        self.max_segment_s = max_segment_s
        self.wait_sensor_s = wait_sensor_s
        self.faults = faults
        self.log = ProgramLog()
        self.phase = rd.RapidPhase.IDLE
        self.job_i = -1              # index into jobs of the segment running
        self.t_phase = time.monotonic()
        self.t_start = self.t_phase
        self.guided_since = float("nan")
        self.arc = False
        self.sensor: Any = None      # the newest SensorData
        self.sensor_t = float("nan")
        self.hb_t = float("nan")     # when the sensor's heartbeat last advanced
        self._restart_at = float("nan")
        self._restarted: set[int] = set()
        self._k = 0
        self._last_cycle_t = time.monotonic()
        self._tick_t = 0.0
        self.ended = threading.Event()
        self._lock = threading.Lock()
        if "packet-loss" in faults:
            self.ctrl.set_loss(0.1, 4.0, seed)
        # the controller's messages: its clock, the RAPID data, the feedback's own time
        ctrl = self.ctrl
        base_build, base_stamp, base_apply = (ctrl._messages.build, ctrl._messages.stamp,
                                              ctrl._apply_reply)
        measured = {"t": time.monotonic()}

        def build(q, T, q_plan, T_plan, running, compute_s):   # noqa: ANN001
            msg = base_build(q, T, q_plan, T_plan, running, compute_s)
            # the fed-back pose is the one the previous cycle recorded (the ring's time of it)
            measured["t"] = self._last_cycle_t
            if self.rapid_data:
                with self._lock:
                    data = rd.RapidData(arc_on=self.arc, segment=self._segment_number(),
                                        phase=self.phase, n_segments=self.n_segments)
                rd.write_rapid_data(msg, data)
            return msg

        def stamp(msg) -> bytes:   # noqa: ANN001
            base_stamp(msg)                 # seqno, tm; its clock is overwritten below
            t = measured["t"] + self.offset  # the pose's measurement on the controller's clock
            for part in (msg.feedBack, msg.planned):
                part.time.sec = int(t)
                part.time.usec = min(999_999, int((t % 1.0) * 1e6))
            return msg.SerializeToString()

        def apply(msg) -> None:   # noqa: ANN001
            self._sensor_reply(msg, base_apply)

        base_send = ctrl._send

        def send(data: bytes) -> Any:
            # the cycle's tick: the arm's step computed next is its pose one period later
            self._tick_t = time.monotonic()
            return base_send(data)

        ctrl._send = send                   # type: ignore[method-assign]
        ctrl._messages.build = build        # type: ignore[method-assign]
        ctrl._messages.stamp = stamp        # type: ignore[method-assign]
        ctrl._apply_reply = apply           # type: ignore[method-assign]

    # ------------------------------------------------------------------ sensor side

    def _segment_number(self) -> int:
        return self.jobs[self.job_i].number if 0 <= self.job_i < len(self.jobs) else 0

    def _sensor_reply(self, msg: Any, base_apply: Any) -> None:
        """A valid reply: its RAPID data, and (GUIDED only) its pose command."""
        rd = self.rd
        now = time.monotonic()
        data = rd.read_sensor_data(msg)
        with self._lock:
            self.log.last_reply_t = now
            if data is not None:
                if self.sensor is None or data.heartbeat != self.sensor.heartbeat:
                    self.hb_t = now
                self.sensor, self.sensor_t = data, now
            seg = self._segment_number()
            # a pose command counts only from a sensor that says it guides this segment: a
            # reply in flight from before the hand-over (a hold on where the robot was) is not
            guided = (self.phase == rd.RapidPhase.GUIDED and data is not None
                      and data.segment == seg and data.state == rd.SensorState.TRACKING)
            if not self.rapid_data:
                # no handshake: RAPID's EGMRunPose ramps in for its first 0.5 s (a reply in
                # flight from before the hand-over is not applied)
                guided = self.phase == rd.RapidPhase.GUIDED and now - self.t_phase > 0.5
            arc = self.arc
        if guided:
            base_apply(msg)
            c = msg.planned.cartesian
            T = np.eye(4)
            from torchseam.core.transforms import quat_to_matrix

            q = np.array([c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3])
            if np.linalg.norm(q) > 0:
                T[:3, :3] = quat_to_matrix(q / np.linalg.norm(q))
            T[:3, 3] = [c.pos.x, c.pos.y, c.pos.z]
            wire = self.log.wire
            if not wire or wire[-1][1] != seg or not np.array_equal(wire[-1][3], T):
                wire.append((now, seg, arc, T))

    # ------------------------------------------------------------------ the program

    def on_cycle(self, ctrl: Any) -> None:
        """RAPID's program, the arc and the truth, once per EGM cycle (controller thread)."""
        rd = self.rd
        now = time.monotonic()
        with self._lock:
            self._program(now)
            seg, arc, guided_since = self._segment_number(), self.arc, self.guided_since
        T = ctrl.tcp_pose()
        # the pose the step just computed is the arm's at the end of the step: a period after
        # this cycle's tick (the ring and the fed-back time say so, whenever this thread ran)
        t_pose = self._tick_t + ctrl.period if self._tick_t else now
        self.log.cycles.append(_Cycle(t_pose, T, arc, seg))
        if self.marks is not None:
            mark = float(self.marks[0])
            if math.isfinite(mark) and mark != self._stall_seen and now >= mark and not arc:
                self._stall_seen = mark
                self.log.arc_off_after_stall_s.append(round(now - mark, 4))
        write_pose(self.ring, self._k, t_pose, self.job_i, arc, guided_since, T)
        self._k += 1
        self._last_cycle_t = t_pose
        if self.phase == rd.RapidPhase.ENDED and now - self.t_phase > 1.0:
            self.ended.set()

    def _event(self, now: float, text: str) -> None:
        self.log.events.append(f"t={now - self.t_start:.2f}s {text}")
        print(f"virtual cell: {text}", flush=True)

    def _stop_robot(self) -> None:
        self.ctrl.arm.rest_at(self.ctrl.arm.q)

    def _program(self, now: float) -> None:  # noqa: C901 - one state machine, read top down
        P = self.rd.RapidPhase
        s = self.sensor
        fresh = s is not None and now - self.hb_t <= self.arc_hold_s
        if self.phase == P.IDLE:
            if fresh or (not self.rapid_data and now - self.log.last_reply_t < 0.1):
                self._next_segment(now)
            elif now - self.t_phase > self.wait_sensor_s:
                self._event(now, f"no sensor answered within {self.wait_sensor_s:g} s: "
                                 "program ended")
                self._end(now)
        elif self.phase == P.TO_START:
            if now - self.t_phase >= self.transfer_s:
                job = self.jobs[self.job_i]
                q, ok = self.ctrl.robot.ik(_tensor(job.T_start @ self.tool_inv)[None],
                                           _tensor(self.ctrl.q)[None])
                if not bool(ok[0]):
                    self._event(now, f"segment {job.name}: start pose out of reach")
                    self.log.outcome[job.number] = "unreachable"
                    self._set(P.TAKEN_BACK, now)
                    return
                self.ctrl.rest_at(q[0].numpy().astype(float))
                self._set(P.GUIDED, now)
                self.guided_since = now
                self.log.last_reply_t = now   # EGM's timeout counts from the hand-over
                self._event(now, f"segment {job.name}: at its start, EGM guides")
        elif self.phase == P.GUIDED:
            self._guided(now, s, fresh)
        elif self.phase == P.TAKEN_BACK:
            self.arc = False
            if now - self.t_phase >= 0.3:
                if self.log.outcome.get(self._segment_number()) == "timeout":
                    self._end(now)
                else:
                    self._next_segment(now)

    def _guided(self, now: float, s: Any, fresh: bool) -> None:
        rd, P = self.rd, self.rd.RapidPhase
        job = self.jobs[self.job_i]
        if not math.isnan(self._restart_at):
            if now - self._restart_at < RESTART_SILENCE_S + 0.2:
                self.arc = False                 # restarting: nothing sent, nothing heard
                self.log.last_reply_t = now
                return
            self._restart_at = float("nan")
        since = self.log.last_reply_t
        if now - since > self.comm_timeout_s:
            self.arc = False
            self._stop_robot()
            self.log.outcome[job.number] = "timeout"
            self.log.stopped_after_timeout_s = now - since
            self._event(now, f"segment {job.name}: EGM communication timeout (no reply for "
                             f"{self.comm_timeout_s:g} s): robot stopped, arc off, program "
                             "ended")
            self._set(P.TAKEN_BACK, now)
            return
        if not self.rapid_data:
            self._old_schema(now, job)
            return
        mine = s is not None and s.segment == job.number
        self.arc = bool(fresh and mine and s.arc_request)
        if mine and s.state in (rd.SensorState.DONE, rd.SensorState.ABORT):
            self.arc = False
            self._stop_robot()
            what = "done" if s.state == rd.SensorState.DONE else "abort"
            self.log.outcome[job.number] = what
            self._event(now, f"segment {job.name}: the sensor says {what}; RAPID takes back")
            self._set(P.TAKEN_BACK, now)
            return
        if now - self.t_phase > self.max_segment_s:
            self.arc = False
            self._stop_robot()
            self.log.outcome[job.number] = "overtime"
            self._event(now, f"segment {job.name}: no end after {self.max_segment_s:.0f} s: "
                             "RAPID takes back")
            self._set(P.TAKEN_BACK, now)
            return
        if ("controller-restart" in self.faults and now - self.guided_since > _fault_at_s(job)
                and job.number not in self._restarted):
            self._restarted.add(job.number)
            self._restart(now)

    def _old_schema(self, now: float, job: SegmentJob) -> None:
        """RAPID without the data channel: its own arc (a distance trigger at the approach's
        end) and EGM's convergence (the torch stood still for a second) end the segment."""
        T = self.ctrl.tcp_pose()
        if self._T_prev is not None:
            d = float(np.linalg.norm(T[:3, 3] - self._T_prev[:3, 3]))
            self._path_mm += d
            if d / self.ctrl.period < STILL_MM_S:
                if math.isnan(self._still_since):
                    self._still_since = now
            else:
                self._still_since = float("nan")
        self._T_prev = T
        welding = self._path_mm >= job.approach_mm
        converged = (welding and not math.isnan(self._still_since)
                     and now - self._still_since > 1.0)
        self.arc = welding and not converged and math.isnan(self._still_since)
        if converged or now - self.t_phase > self.max_segment_s:
            self.arc = False
            self._stop_robot()
            self.log.outcome[job.number] = "done" if converged else "overtime"
            self._event(now, f"segment {job.name}: EGM converged (the torch stood still): "
                             "RAPID takes back" if converged else
                        f"segment {job.name}: no end after {self.max_segment_s:.0f} s")
            self._set(self.rd.RapidPhase.TAKEN_BACK, now)
            self._path_mm, self._T_prev, self._still_since = 0.0, None, float("nan")

    def _restart(self, now: float) -> None:
        """EGM restarts: silent for RESTART_SILENCE_S (robot stopped, arc off), then a new
        sequence (numbers from 1, the clock going on); RAPID's segment goes on, guided, from
        where the robot stands."""
        self.arc = False
        self._stop_robot()
        self._restart_at = now
        self._event(now, "controller-restart: EGM silent, a new sequence follows")
        self.ctrl.inject("silence", int(RESTART_SILENCE_S / self.ctrl.period))
        self.ctrl._messages._seqno = 0

    def _set(self, phase: Any, now: float) -> None:
        self.phase, self.t_phase = phase, now
        if phase != self.rd.RapidPhase.GUIDED:
            self.arc = False

    def _next_segment(self, now: float) -> None:
        self.job_i += 1
        self.guided_since = float("nan")
        if self.job_i >= len(self.jobs):
            self._event(now, "program ended")
            self._end(now)
            return
        self._set(self.rd.RapidPhase.TO_START, now)
        self._event(now, f"segment {self.jobs[self.job_i].name}: moving to its start")

    def _end(self, now: float) -> None:
        self.arc = False
        self._stop_robot()
        self.job_i = len(self.jobs)
        self._set(self.rd.RapidPhase.ENDED, now)

    # ------------------------------------------------------------------ running

    @property
    def address(self) -> tuple[str, int]:
        return self.ctrl.address

    def run(self) -> None:
        """Cycle until the program ended (a thread of its own, see :meth:`start`)."""
        self.ctrl.run(None, on_cycle=self.on_cycle)

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="virtual-irc5", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the cycle thread, then close the controller's socket (in that order: a cycle
        still sending on a closed socket would log a send error)."""
        self.ctrl._stop.set()
        thread = getattr(self, "_thread", None)
        if thread is not None:
            thread.join(timeout=5.0)
        self.ctrl.stop()


def _fault_at_s(job: SegmentJob) -> float:
    """When a mid-segment fault starts, s after the hand-over: half way along the weld."""
    return (job.approach_mm + 0.5 * job.length_mm) / 8.0


def _tensor(x: np.ndarray) -> Any:
    import torch

    return torch.tensor(np.asarray(x, float))


# --------------------------------------------------------------------------- the camera


@dataclass(frozen=True)
class CameraSpec:
    """What the camera process needs (picklable: it starts with ``spawn``)."""

    cell: CellConfig
    part: PartConfig
    noise: NoiseConfig
    level: float
    seed: int
    family: str | None
    rotations: tuple[float, ...]       # the part's turn per job
    fault_at_s: tuple[float, ...]      # per job, s after the hand-over
    latency_s: float
    faults: tuple[str, ...]
    port: int


def camera_main(spec: CameraSpec, ring: Any, port_out: Any, stop: Any, marks: Any) -> None:
    """The laser camera: expose at the frame rate, render from the robot's pose at the
    exposure time, deliver ``latency_s`` later, stamped on the camera's own clock."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent ends it
    import cv2

    from torchseam.live.framestream import FrameStreamServer
    from torchseam.sim.scene import Scene
    from torchseam.sim.sequence import SensorRenderer

    cv2.setNumThreads(1)
    server = FrameStreamServer("127.0.0.1", spec.port)
    port_out.send(server.address[1])
    scenes = [Scene(spec.part, r) for r in spec.rotations]
    renderers: dict[int, Any] = {}
    period = 1.0 / spec.cell.process.frame_rate_hz
    cam_t0 = time.monotonic() - 1000.0 * (1 + spec.seed % 7)   # the camera's own epoch
    rng = np.random.default_rng(spec.seed + 99)
    t_next = time.monotonic() + period
    index = 0
    sent_late = 0
    stalled = False
    try:
        while not stop.is_set():
            t_exp = t_next
            t_next += period
            _sleep_until(t_exp + 0.0045)       # the controller's pose at t_exp is recorded
            rec = read_poses(ring, 16)
            if len(rec) < 2:
                continue
            pose = _pose_at(rec, t_exp)
            if pose is None:
                continue
            T, job, arc, guided = pose
            index += 1
            if job < 0 or job >= len(scenes):
                continue                       # between programs: nothing to see
            r = renderers.get(job)
            if r is None:
                r = renderers[job] = SensorRenderer(spec.cell, scenes[job], spec.noise,
                                                    spec.level, spec.seed * 10 + job,
                                                    spec.family)
            # at the exposure the weld asked for last (1: as configured; its automatic
            # exposure, camera.auto_exposure, asks on the stream)
            frame, _ = r.render(T, t_exp - guided if math.isfinite(guided) else 0.0,
                                arc_on=arc, exposure=server.exposure)
            into = t_exp - guided if math.isfinite(guided) else -1.0
            fault = math.isfinite(guided) and spec.fault_at_s[job] <= into < (
                spec.fault_at_s[job] + FAULT_S)
            if fault and "camera-stall" in spec.faults:
                if not stalled:
                    stalled = True
                    marks[0] = t_exp + spec.latency_s   # when this frame was due
                continue
            stalled = False
            if fault and "camera-drop" in spec.faults and rng.random() < 0.5:
                continue
            due = t_exp + spec.latency_s
            if time.monotonic() > due + 0.002:
                sent_late += 1
                marks[1] = float(sent_late)
            _sleep_until(due)
            if server.send(index, int((t_exp - cam_t0) * 1e9), frame):
                marks[2] += 1.0
    finally:
        server.close()


def _pose_at(rec: np.ndarray, t: float) -> tuple[np.ndarray, int, bool, float] | None:
    """The recorded pose at ``t`` (linear between the two records around it)."""
    ts = rec[:, 0]
    i = int(np.searchsorted(ts, t))
    if i == 0 or i >= len(ts):
        i = min(max(i, 1), len(ts) - 1)
    a, b = rec[i - 1], rec[i]
    w = float(np.clip((t - a[0]) / (b[0] - a[0]), 0.0, 1.0)) if b[0] > a[0] else 1.0
    near = b if w > 0.5 else a
    Ta, Tb = a[4:20].reshape(4, 4), b[4:20].reshape(4, 4)
    T = Tb.copy() if w > 0.5 else Ta.copy()
    T[:3, 3] = (1 - w) * Ta[:3, 3] + w * Tb[:3, 3]
    return T, int(near[1]), bool(near[2] > 0.5), float(near[3])


def _sleep_until(t: float) -> None:
    while True:
        d = t - time.monotonic()
        if d <= 0:
            return
        time.sleep(min(d, 0.05))


# --------------------------------------------------------------------------- the summary


def summarise(log: ProgramLog, jobs: list[SegmentJob], scenes: list[Any], gate_for: Any,
              angles: list[tuple[float, float]], max_step_mm: float, t_start: float,
              info: dict[str, Any], frames_sent: float = 0, frames_late: float = 0
              ) -> dict[str, Any]:
    """The truth of the run (see the module docstring)."""
    from torchseam.core.transforms import pose_matrix
    from torchseam.live.ring import torch_axis_errors

    seam_d: list[float] = []
    still_s = off_s = 0.0
    per_seg: dict[str, dict[str, Any]] = {}
    cyc = log.cycles
    num_to_i = {j.number: i for i, j in enumerate(jobs)}
    curves = {}
    for i, sc in enumerate(scenes):
        curves[i] = sc.true_joint.dense_seam().point
    for k in range(1, len(cyc)):
        c, p = cyc[k], cyc[k - 1]
        if not c.arc or c.seg not in num_to_i:
            continue
        i = num_to_i[c.seg]
        dt = c.t - p.t
        T_B_T = scenes[i].part_pose(0.0)
        tip = invert(T_B_T)[:3, :3] @ c.T[:3, 3] + invert(T_B_T)[:3, 3]
        dist = float(np.min(np.linalg.norm(curves[i] - tip, axis=1))) if k % 5 == 0 else None
        if dist is not None:
            seam_d.append(dist)
            if dist > OFF_SEAM_MM:
                off_s += 5 * dt
        v = float(np.linalg.norm(c.T[:3, 3] - p.T[:3, 3])) / max(dt, 1e-9)
        if v < STILL_MM_S:
            still_s += dt
        seg = per_seg.setdefault(jobs[i].name, {"welded_mm": 0.0})
        seg["welded_mm"] += float(np.linalg.norm(c.T[:3, 3] - p.T[:3, 3]))
    axis: list[float] = []
    unsafe = 0
    unsafe_why: list[str] = []
    for i, job in enumerate(jobs):
        wire = [w for w in log.wire if w[1] == job.number]
        if not wire:
            continue
        T = np.array([w[3] for w in wire])
        gate = gate_for(i)
        bad = ~np.isfinite(T).all(axis=(1, 2))
        import torch

        verdict = gate.check(torch.tensor(T[~bad]))
        ok = verdict.ok.numpy()
        steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        n_step = int((steps > max_step_mm * (1 + 1e-9)).sum())
        unsafe += int(bad.sum() + (~ok).sum() + n_step)
        for k in np.flatnonzero(~ok)[:5]:
            unsafe_why.append(f"segment {job.name}: gate: {verdict.reasons[int(k)]}")
        if n_step:
            unsafe_why.append(f"segment {job.name}: {n_step} step(s) > {max_step_mm:g} mm "
                              f"(largest {steps.max():.2f} mm)")
        welded = [w for w in wire if w[2]]
        if welded:
            Tw = np.array([w[3] for w in welded])
            ang, _ = torch_axis_errors(scenes[i], Tw[:, :3, 3], Tw[:, :3, :3],
                                       np.zeros(len(Tw)), angles=angles[i])
            axis += [float(a) for a in ang]
        per_seg.setdefault(job.name, {"welded_mm": 0.0})
    del pose_matrix
    d = np.array(seam_d)
    ax = np.array(axis)
    incomplete = []
    for job in jobs:
        s = per_seg.setdefault(job.name, {"welded_mm": 0.0})
        s["asked_mm"] = job.length_mm
        s["outcome"] = log.outcome.get(job.number, "not run")
        s["unwelded_mm"] = round(max(0.0, job.length_mm - s["welded_mm"]), 3)
        s["welded_mm"] = round(s["welded_mm"], 3)
        if s["outcome"] != "done" or s["unwelded_mm"] > 0.5:
            incomplete.append({"segment": job.name, "reason": f"{s['outcome']}, "
                               f"{s['welded_mm']:.1f} of {job.length_mm:.1f} mm welded"})

    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(x**2))) if len(x) else float("nan")

    return {
        **info,
        "seam_rmse_mm": rms(d), "seam_max_mm": float(d.max()) if len(d) else float("nan"),
        "axis_rmse_deg": rms(ax), "axis_max_deg": float(ax.max()) if len(ax) else float("nan"),
        "axis_within_1deg": int((ax <= 1.0).sum()), "poses_welded": len(ax),
        "unsafe_poses_sent": unsafe, "unsafe_reasons": unsafe_why,
        "arc_on_while_still_s": round(still_s, 3),
        "arc_on_off_seam_s": round(off_s, 3),
        "segments": per_seg,
        "segments_incomplete": incomplete,
        "events": list(log.events),
        "arc_off_after_camera_stall_s": list(log.arc_off_after_stall_s),
        "camera_frames_sent": int(frames_sent), "camera_frames_late": int(frames_late),
        "robot_stopped_after_comm_loss_s": (None if math.isnan(log.stopped_after_timeout_s)
                                            else round(log.stopped_after_timeout_s, 3)),
        "controller": {"cycles": len(cyc)},
    }


# --------------------------------------------------------------------------- the command


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_ignoring_sigint(proc: Any) -> None:
    """Start ``proc`` (a spawned process) with SIGINT ignored from its first instruction (a
    Ctrl-C reaches the whole process group; the parent ends the child): the parent ignores it
    meanwhile, the disposition passes through exec, and a SIGINT sent to the parent in that
    window stays pending (blocked) until its own handler is back."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        proc.start()
    finally:
        signal.signal(signal.SIGINT, handler)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def run_virtual_cell(args: Any) -> int:  # noqa: C901 - the command, read top down
    """``torchseam virtual-cell`` (see the module docstring); returns the exit code."""
    import torch

    from torchseam.core.config import load_cell, load_noise, load_part
    from torchseam.core.report import prepare_out_dir, write_json_atomic
    from torchseam.live.parts import load_live_parts
    from torchseam.plan.preflight import preflight
    from torchseam.robot.reach import ReachGate
    from torchseam.sim.scene import Scene

    torch.set_num_threads(1)
    cell, part, noise = load_cell(), load_part(args.part), load_noise()
    try:
        level = noise.level(args.noise)
    except ValueError as e:
        raise TorchseamError(f"--noise: {e}") from None
    parts = load_live_parts()
    report = preflight(cell, part, config=parts.plan, robot=parts.robot,
                       part_name=str(args.part))
    if not report.ok:
        print(report.text(), file=sys.stderr)
        raise TorchseamError(f"the robot cannot weld {args.part}: pre-flight refused "
                             f"segment(s) {', '.join(report.refused)}; the virtual cell has "
                             "no program to run")
    out = prepare_out_dir(args.out, "torchseam virtual-cell")
    plan = report.plan
    jobs: list[SegmentJob] = []
    scenes: list[Any] = []
    angles: list[tuple[float, float]] = []
    gates: list[Any] = []
    approach = cell.process.look_ahead_mm + parts.plan.approach_mm
    for seg in plan.segments:
        if seg.name not in args.segments:
            continue
        scene = Scene(plan.part, seg.rotation_deg)
        s0 = float(scene.s_at(np.array([seg.phi_start]))[0])
        seg_len = (float(scene.s_at(np.array([seg.phi_end]))[0]) - s0) % scene.seam_length_mm
        if args.length_mm is not None:
            seg_len = min(seg_len, args.length_mm)
        T0 = plan.nominal_tcp(seg, np.array([s0 - approach]))[0]
        jobs.append(SegmentJob(seg.index + 1, seg.name, T0, seg.rotation_deg, seg_len,
                               approach))
        scenes.append(scene)
        angles.append((float(seg.angles[0]), float(seg.angles[1])))
        gates.append(ReachGate(parts.robot, cell=cell, part=plan.part,
                               part_pose_mm=scene.T_B_Tnom))
    if args.program == "latency":
        # RAPID's latency routine: one guided motion at the first segment's start, as long as
        # the sensor moves the robot (torchseam calibrate latency), nothing welded
        jobs = [dataclasses.replace(jobs[0], length_mm=0.0)]
        scenes, angles, gates = scenes[:1], angles[:1], gates[:1]
    # from here a signal is taken, not raised: the camera's process and the controller's
    # thread are started and must be ended, and the run still reports (exit 128 + signal)
    stopping: dict[str, Any] = {"sig": 0, "vc": None}

    def on_signal(signum: int, _frame: Any) -> None:
        stopping["sig"] = signum
        if stopping["vc"] is not None:
            stopping["vc"].ended.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    ctx = mp.get_context("spawn")
    ring = _shared_ring(ctx)
    stop = ctx.Event()
    port_rx, port_tx = ctx.Pipe(duplex=False)
    marks = ctx.Array("d", [float("nan"), 0.0, 0.0], lock=False)  # stall due, late, sent
    spec = CameraSpec(cell, plan.part, noise, level, args.seed, None,
                      tuple(j.rotation_deg for j in jobs), tuple(_fault_at_s(j) for j in jobs),
                      args.camera_latency_ms / 1e3, tuple(args.fault), 0)
    cam = ctx.Process(target=camera_main, args=(spec, ring, port_tx, stop, marks),
                      name="laser-camera", daemon=True)
    _start_ignoring_sigint(cam)
    deadline = time.monotonic() + 60.0
    while not port_rx.poll(0.1):
        if stopping["sig"] or time.monotonic() > deadline:
            stop.set()
            cam.terminate()
            cam.join(timeout=5.0)
            if stopping["sig"]:
                print(f"virtual cell: interrupted by {signal.Signals(stopping['sig']).name} "
                      "while its camera started; nothing ran", flush=True)
                return 128 + stopping["sig"]
            raise TorchseamError("the virtual camera did not start within 60 s")
    cam_port = int(port_rx.recv())
    sensor_port = free_udp_port()
    comm_timeout = args.comm_timeout_s
    max_seg_s = max((j.approach_mm + j.length_mm) / cell.process.weld_speed_mm_s for j in jobs
                    ) * 4 + 60.0
    vc = VirtualController(cell, parts.egm, parts.robot, jobs, ring,
                           ("127.0.0.1", sensor_port), clock_offset_s=args.clock_offset_s,
                           comm_timeout_s=comm_timeout, arc_hold_ms=args.arc_hold_ms,
                           transfer_s=1.0, faults=tuple(args.fault), seed=args.seed,
                           max_segment_s=max_seg_s, wait_sensor_s=args.wait_sensor_s,
                           n_segments=len(plan.segments), marks=marks,
                           rapid_data=args.rapid_data == "on")
    # the robot waits at the first segment's start pose's neighbourhood: its home
    weld_cell = WeldCell(
        calibration=cell,
        camera=CameraLink(source=f"tcp://127.0.0.1:{cam_port}",
                          latency_ms=float(args.camera_latency_ms)),
        controller=ControllerLink(host="127.0.0.1", port=sensor_port,
                                  controller_host="127.0.0.1", controller_port=vc.address[1],
                                  cycle_ms=vc.ctrl.period * 1e3,
                                  # a pose is the arm's at the end of one cycle's step and
                                  # leaves at the next tick: a cycle old at the least
                                  feedback_delay_ms=vc.ctrl.period * 1e3,
                                  rapid_data=args.rapid_data == "on"))
    stopping["vc"] = vc
    if stopping["sig"]:
        vc.ended.set()
    vc.start()
    if args.write_cell is not None and not stopping["sig"]:
        save_weld_cell(weld_cell, args.write_cell,
                       header="# written by torchseam virtual-cell: the virtual camera's "
                              "calibration, its frame stream, the virtual IRC5's EGM\n")
        print(f"virtual cell: cell file {args.write_cell}", flush=True)
    print(f"virtual cell: camera tcp://127.0.0.1:{cam_port} (latency "
          f"{args.camera_latency_ms:g} ms), controller EGM 127.0.0.1:{vc.address[1]} -> "
          f"sensor 127.0.0.1:{sensor_port}, clock offset {args.clock_offset_s:g} s; RAPID "
          f"program: segment(s) {', '.join(j.name for j in jobs)}; waiting for the sensor",
          flush=True)
    try:
        while not vc.ended.wait(0.2):
            if not cam.is_alive():
                vc._event(time.monotonic(), "the camera process died")
                break
    finally:
        vc.stop()
        stop.set()
        cam.join(timeout=5.0)
        if cam.is_alive():
            cam.terminate()
    info = {"program": args.program, "part": str(args.part), "segments_asked": args.segments,
            "length_mm": args.length_mm, "noise": level, "seed": args.seed,
            "faults": list(args.fault), "camera_latency_ms": args.camera_latency_ms,
            "clock_offset_s": args.clock_offset_s, "comm_timeout_s": comm_timeout,
            "rapid_data": args.rapid_data,
            "interrupted": bool(stopping["sig"])}
    # the step a pose may make: the link's limit for the IPI step (torchseam weld's link)
    max_step = max(parts.egm.safety.max_step_mm, 1.25 * cell.process.step_mm)
    summary = summarise(vc.log, jobs, scenes, lambda i: gates[i], angles, max_step,
                        vc.t_start, info, frames_sent=marks[2], frames_late=marks[1])
    write_json_atomic(out / "summary.json", summary)
    print(summary_line(summary, out / "summary.json",
                       signal.Signals(stopping["sig"]).name if stopping["sig"] else None),
          flush=True)
    if stopping["sig"]:
        return 128 + stopping["sig"]
    return 0


def summary_line(s: dict, path: Any, interrupted_by: str | None = None) -> str:
    """The virtual cell's last line: the truth's figures of what was welded (no seam figures
    when no pose was: a program interrupted, or the latency calibration's), and how it ended."""
    how = f"interrupted by {interrupted_by}; " if interrupted_by else ""
    seam = (f"seam RMSE {s['seam_rmse_mm']:.3f} mm, max {s['seam_max_mm']:.3f} mm, axis within "
            f"1 deg {s['axis_within_1deg']} of {s['poses_welded']}" if s["poses_welded"]
            else f"no pose welded (program {s['program']})")
    return (f"virtual cell: {how}{seam}, unsafe poses {s['unsafe_poses_sent']}, arc on while "
            f"still {s['arc_on_while_still_s']:.2f} s, off seam {s['arc_on_off_seam_s']:.2f} s; "
            f"summary {path}")


__all__ = ["VIRTUAL_FAULTS", "VirtualController", "run_virtual_cell", "camera_main",
           "summarise", "summary_line", "os"]
