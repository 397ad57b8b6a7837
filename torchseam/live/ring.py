"""The whole ring, segment by segment, in open loop: see, locate, plan (METHOD.md 5-6).

For each of the six segments the positioner turns the part, the robot runs the *nominal*
(design) path with the sensor 20 mm ahead of the torch, the tracker follows the feature point
through the arc noise, every frame is located in 3D, and the look-ahead buffer turns the
located points into the commanded path (IPI steps, torch frames from ECAL's arms). The run
keeps the simulator's truth, so it measures what the issue asks: the 3D location error, the
planned path's error and the nominal path's error against the true seam, and the torch axis
against the joint bisector. The closed loop (``torchseam demo``) commands the robot with the
planned path instead.

Each segment starts with an approach: the torch starts ``look_ahead + approach_mm`` before
the segment with the arc off, so the stripe has seen the segment start (and TIPM has found the
stripe on a clean frame) when the arc strikes.

The segments, the part's placement and the torch's angles are the weld plan's
(:func:`torchseam.plan.preflight.preflight`: the configured plan when the IRB 1410 can weld it,
else the one the search finds with the reachability gate); :func:`write_ring_poses` writes the
planned torch poses in the format of ``torchseam robot check``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchseam.core.config import CellConfig, NoiseConfig, PartConfig
from torchseam.core.poses_csv import write_pose_csv
from torchseam.core.transforms import apply, invert
from torchseam.geometry.torch_frame import quaternions, tilt, torch_frame
from torchseam.live.locate import Location, SeamLocator
from torchseam.live.parts import LiveParts
from torchseam.plan.path import Located, LookAheadBuffer
from torchseam.plan.preflight import PlanReport, preflight
from torchseam.plan.weld import SegmentPlan, torch_angles
from torchseam.sim.joint import SeamSample
from torchseam.sim.scene import Scene, torch_frames
from torchseam.sim.sequence import FrameTruth, SequenceSpec, simulate
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import make_tracker


@dataclass
class SegmentRun:
    """One segment's frames, locations, commands and the truth to judge them by."""

    segment: SegmentPlan
    truths: list[FrameTruth] = field(default_factory=list)
    locations: list[Location] = field(default_factory=list)
    entries: list[Located | None] = field(default_factory=list)   # buffer entry per frame
    commands: list[np.ndarray] = field(default_factory=list)       # (3,) ip, base mm
    rotations: list[np.ndarray] = field(default_factory=list)      # (3, 3) torch frames
    quats: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    frame_ok: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # per command
    command_t: list[float] = field(default_factory=list)
    nominal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    scene: Scene | None = None
    weld_t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per command: when the
    # torch gets there at weld speed, s (from the segment's arc strike)
    report: PlanReport | None = None  # the weld plan this run followed and its pre-flight


def run_ring(cell: CellConfig, part: PartConfig, noise: NoiseConfig, level: float, seed: int,
             tracker: str = "anchored", segments: list[int] | None = None,
             progress: Callable[[int], None] | None = None,
             report: PlanReport | None = None,
             length_mm: float | None = None,
             model_path: str | Path | None = None, *, parts: LiveParts) -> list[SegmentRun]:
    """Weld the ring in open loop; returns one :class:`SegmentRun` per segment.

    ``segments``: which of the six to run (default all). ``progress(n)`` is called per frame.
    ``parts``: the planning settings, the arm model (the pre-flight's gate), TIPM and ECAL
    (:func:`~torchseam.live.parts.load_live_parts` reads the shipped ones).
    ``report``: the weld plan's pre-flight (default :func:`~torchseam.plan.preflight.preflight`
    of ``part`` with ``parts``); its plan's placement, segments and torch angles are used.
    When the robot cannot weld that plan the table goes to stderr and the open-loop run goes
    on (it moves no robot; the closed loop refuses such a plan). ``length_mm`` runs only the
    first mm of each segment (quick runs and tests).
    """
    proc = cell.process
    plan = parts.plan
    if report is None:
        report = preflight(cell, part, config=plan, robot=parts.robot)
        if not report.ok:
            print(report.text() + "\n(open loop: the ring is run all the same)", file=sys.stderr)
    part = report.plan.part  # placed as planned
    runs = []
    t0 = 0.0
    for seg in report.plan.segments:
        if segments is not None and seg.index not in segments:
            continue
        scene = Scene(part, seg.rotation_deg)
        s0 = float(scene.s_at(np.array([seg.phi_start]))[0])
        s1 = float(scene.s_at(np.array([seg.phi_end]))[0])
        seg_len = (s1 - s0) % scene.seam_length_mm
        if length_mm is not None:
            seg_len = min(seg_len, float(length_mm))
        approach = proc.look_ahead_mm + plan.approach_mm
        mm_per_frame = proc.weld_speed_mm_s / proc.frame_rate_hz
        arc_on = int(np.ceil(approach / mm_per_frame))
        n_frames = arc_on + int(np.ceil((seg_len + plan.approach_mm) / mm_per_frame))
        spec = SequenceSpec(n_frames=n_frames, level=level, seed=seed * 10 + seg.index,
                            start_mm=s0 - approach, rotation_deg=seg.rotation_deg,
                            arc_on_frame=arc_on, t0_s=t0)
        run = SegmentRun(seg, scene=scene, report=report)
        # the part's joint decides what is tracked (a fillet: ``tracker``; else its profile),
        # as in the closed loop
        frame_tracker = (make_tracker(tracker, parts.tipm, model_path=model_path)
                         if part.joint == "fillet"
                         else parts.tracker(tracker, part.joint, model_path))
        locator = SeamLocator(cell, frame_tracker, parts.tipm, parts.ecal)
        buf = LookAheadBuffer(maxlen=plan.buffer_points, smooth_mm=plan.smooth_mm,
                              outlier_mm=plan.outlier_mm)
        T_F_C_inv = invert(cell.hand_eye.matrix())
        for k, (img, truth) in enumerate(simulate(cell, part, noise, spec)):
            T_B_F = truth.T_B_C @ T_F_C_inv  # the robot's reported flange pose
            if k == 0:
                locator.start(img)
                loc = Location(truth.uv * np.nan, 0, np.full(3, np.nan), np.full((2, 3), np.nan),
                               False, False)
            entry = None
            if k > 0:
                loc = locator.step(img, T_B_F)
                # what the live loop takes as located: a point with the stripe seen around it
                if np.all(np.isfinite(loc.p)) and loc.status != TrackStatus.LOST and loc.arms_ok:
                    entry = buf.push(loc.p, loc.q, truth.t_s, guessed=loc.arms_fallback)
            run.entries.append(entry)
            run.truths.append(truth)
            run.locations.append(loc)
            if progress:
                progress(1)
        t0 += n_frames / proc.frame_rate_hz
        _plan_segment(run, buf, cell, s0, seg_len)
        if run.commands:  # at weld speed from the arc strike (the first command's time)
            steps = np.linalg.norm(np.diff(np.array(run.commands), axis=0), axis=1)
            run.weld_t = run.truths[arc_on].t_s + np.concatenate(
                [[0.0], np.cumsum(steps)]) / proc.weld_speed_mm_s
        # judge the located points the plan's fits did not reach (the approach, the stripe
        # past the segment end), for the located-point statistics
        entries = list({id(e): e for e in run.entries if e is not None}.values())
        judge = LookAheadBuffer(maxlen=len(entries) + 1, smooth_mm=plan.smooth_mm,
                                outlier_mm=plan.outlier_mm)
        judge.points.extend(entries)
        judge.screen()
        runs.append(run)
    return runs


def _plan_segment(run: SegmentRun, buf: LookAheadBuffer, cell: CellConfig, s0: float,
                  seg_len: float) -> None:
    """IPI commands along the located points from the segment start to its end."""
    scene = run.scene
    assert scene is not None
    start = scene.nominal_tcp(np.array([s0]))[0][:3, 3]
    # the torch starts where the located path passes the segment start (the points before
    # it stay in the buffer: the fits around the first commands need both sides)
    if not buf.points:
        return
    d = [np.linalg.norm(loc.p - start) for loc in buf.points]
    cp = buf.fit(int(np.argmin(d)))[0]
    step = cell.process.step_mm
    travelled = 0.0
    ips, tangents, arms = [], [], []
    while travelled < seg_len - 1e-6:
        nxt = buf.next_command(cp, step)
        if nxt is None:
            break
        ip, tangent, arm_dirs = nxt
        if tangent is None:
            tangent = (ip - cp) / np.linalg.norm(ip - cp)
        travelled += float(np.linalg.norm(ip - cp))
        run.command_t.append(min(buf.points, key=lambda L: np.linalg.norm(L.p - ip)).t_s)
        ips.append(ip)
        tangents.append(tangent)
        arms.append(arm_dirs)
        cp = ip
    if not ips:
        return
    P = torch.tensor(np.array(ips))
    A = torch.tensor(np.array(arms))
    # where the torch points on the nominal path (open loop: the robot follows it): arms in
    # one line (a butt's straight stripe) give the frame across that line on this side
    steps = np.linalg.norm(np.diff(np.array(ips), axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(steps)])
    facing = torch.tensor(scene.nominal_tcp(s0 + along)[:, :3, 2])
    R, ok = torch_frame(P, P + A[:, 0], P + A[:, 1], tangent=torch.tensor(np.array(tangents)),
                        facing=facing)
    work, travel, roll = run.segment.angles
    R = tilt(R, work, travel)
    if roll:
        R = R @ torch.as_tensor(torch_angles(0.0, 0.0, roll), dtype=R.dtype)
    # no torch frame (no arms near the point, degenerate arms): keep the last good one and
    # say so (the axis error counts it as missing), never an identity or NaN pose
    for i in range(len(R)):
        if not bool(ok[i]) and i > 0:
            R[i] = R[i - 1]
    run.frame_ok = ok.numpy()
    run.commands = list(np.array(ips))
    run.rotations = list(R.numpy())
    run.quats = quaternions(R).numpy()
    run.nominal = scene.nominal_tcp(s0 + np.arange(0.0, seg_len, step))[:, :3, 3]


def torch_axis_errors(scene: Scene, p: np.ndarray, R: np.ndarray, t_s: np.ndarray,
                      seam: SeamSample | None = None, *, angles: tuple[float, float]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Torch axis of poses (``p`` (N, 3) mm, ``R`` (N, 3, 3), robot base) against the true
    one at the nearest point of the true seam, with the part where it was at ``t_s`` (N,):
    ``(angle (N,) degrees, distance to that seam point (N,) mm)``. The true frame gets the
    work and travel ``angles`` (the segment's: :attr:`SegmentPlan.angles`) as the planned one
    does (a roll about the torch axis does not move it). ``seam``: the true seam densely
    sampled (default: 20 001 points round it)."""
    if seam is None:
        seam = scene.true_joint.dense_seam()
    frames = torch.tensor(torch_frames(seam)[:, :3, :3])
    z_T = tilt(frames, *angles)[:, :, 2].numpy()
    angle, dist = np.full(len(p), np.nan), np.full(len(p), np.nan)
    for i in range(len(p)):
        T_B_T = scene.part_pose(float(t_s[i]))
        p_T = apply(invert(T_B_T), p[i])
        k = int(np.argmin(np.linalg.norm(seam.point - p_T, axis=1)))
        dist[i] = np.linalg.norm(seam.point[k] - p_T)
        angle[i] = np.degrees(np.arccos(np.clip(R[i][:, 2] @ (T_B_T[:3, :3] @ z_T[k]), -1, 1)))
    return angle, dist


def ring_errors(runs: list[SegmentRun]) -> dict[str, np.ndarray]:
    """Per-point errors against the truth, pooled over segments (mm, px, degrees).

    ``located_mm`` (arc-on frames, NaN where nothing was located) and ``used`` (bool, the
    same frames: the point went into the look-ahead buffer, with ECAL's arms around it, and
    was not flagged as off the smooth seam through its neighbours) come per frame;
    ``nominal_mm`` per nominal path point; the rest per command, with ``command_segment``
    (the segment's letter) and ``command_index`` (its command number in that segment).
    """
    loc3d, pix, used, planned, nominal, axis = [], [], [], [], [], []
    seg_of, index_of = [], []
    for run in runs:
        scene = run.scene
        assert scene is not None  # run_ring gives every run its scene
        entries = run.entries or [None] * len(run.truths)
        for t, loc, e in zip(run.truths, run.locations, entries, strict=True):
            if not t.arc_on:
                continue
            pix.append(np.linalg.norm(loc.uv - t.uv) if np.all(np.isfinite(loc.uv)) else np.nan)
            loc3d.append(np.linalg.norm(loc.p - t.seam_B) if np.all(np.isfinite(loc.p))
                         else np.nan)
            used.append(e is not None and not e.flagged)
        if not run.commands:
            continue
        s = scene.true_joint.dense_seam()
        # the part as it was when the stripe saw each point
        ax, dist = torch_axis_errors(scene, np.array(run.commands), np.array(run.rotations),
                                     np.array(run.command_t), s, angles=run.segment.angles[:2])
        planned += list(dist)
        axis += list(np.where(run.frame_ok, ax, np.nan))
        seg_of += [run.segment.name] * len(ax)
        index_of += list(range(len(ax)))
        T_B_T = scene.part_pose(run.truths[len(run.truths) // 2].t_s)
        curve = apply(T_B_T, s.point)
        for p in run.nominal:
            nominal.append(np.min(np.linalg.norm(curve - p, axis=1)))
    return {k: np.array(v) for k, v in (("located_mm", loc3d), ("used", used),
                                         ("pixel_px", pix),
                                         ("planned_mm", planned), ("nominal_mm", nominal),
                                         ("axis_deg", axis), ("command_segment", seg_of),
                                         ("command_index", index_of))}


def write_ring_poses(runs: list[SegmentRun], path: str | Path) -> Path:
    """``poses.csv`` of a ring: every planned command's torch TCP pose in the base frame (t,
    x, y, z, q1..q4; ``t`` when the torch gets there at weld speed), segment after segment, in
    the format ``torchseam robot check`` reads (:func:`~torchseam.core.poses_csv.
    write_pose_csv`). The part turns between segments: check a segment other than a with its
    turned part (``torchseam plan --out`` writes ``part_<s>.yaml``)."""
    have = [r for r in runs if r.commands]
    if not have:
        return write_pose_csv(path, np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0))
    return write_pose_csv(path, np.concatenate([np.array(r.commands) for r in have]),
                          np.concatenate([r.quats for r in have]),
                          np.concatenate([r.weld_t for r in have]))
