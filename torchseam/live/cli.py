"""``torchseam demo`` (the closed-loop weld of the simulated T joint, with a report folder) and
``torchseam replay`` (recorded frames through the live loop, open loop)."""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import sys
import time
from pathlib import Path
from typing import Any

from torchseam.core.cliargs import (
    MAX_SEED,
    model_arg,
    out_dir_arg,
    out_file_arg,
    seed_arg,
    segments_arg,
)
from torchseam.core.config import (
    JOINT_PROFILES,
    MAX_NOISE_LEVEL,
    load_cell,
    load_noise,
    load_part,
)
from torchseam.core.errors import TorchseamError
from torchseam.core.poses_csv import NORM_TOLERANCE
from torchseam.core.report import ReportError, format_table
from torchseam.core.signals import EXIT_SIGNAL, SignalStop
from torchseam.live.names import FAULTS
from torchseam.track.names import TRACKERS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="weld a simulated part (default the T joint) in closed loop and write a report",
        description="Weld a part (default the 203/152 mm T joint) in six segments in closed "
                    "loop, with its weld plan: the pre-flight (as `torchseam plan`) first "
                    "chooses the placement, where the segments start and the torch's angles, "
                    "and checks every pose with the reachability gate; then the simulator "
                    "renders what the sensor sees from where the simulated robot is, and the "
                    "live loop tracks (EAKF-STC), locates, plans and guides the simulated IRB "
                    "1410 over EGM. Prints the plan and a summary table and writes plots, a "
                    "video, summary.json, messages.txt and poses.csv (every pose sent, as "
                    "`torchseam robot check` reads them) into --out, a folder of the run's own "
                    "(an earlier run's report there is moved aside to OUT.previous-N, said on "
                    "stderr; a RUNNING file marks the run until summary.json, written last, is "
                    "there). Exit code 1 when a segment was not welded: its end not reached, "
                    "or more than 0.5 mm of its seam passed with the arc out (summary.json: "
                    "segments_incomplete with the reason, unwelded_mm, arc_gaps); 2 when the "
                    "robot cannot weld the part (the pre-flight table names the segment and "
                    "the reason; nothing moves) or on bad input; 3 when the report could not "
                    "be written (a full disk, a permission: one line names the file); 130 / "
                    "143 on SIGINT / SIGTERM (the weld stops at the next frame, the report of "
                    "what was done is written, summary.json marked interrupted).")
    p.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml; "
                                             "others in configs/parts/)")
    p.add_argument("--noise", default="heavy",
                   help="arc-noise level: a name from configs/noise.yaml or a number in "
                        f"[0, {MAX_NOISE_LEVEL:g}] (default heavy)")
    p.add_argument("--seed", type=seed_arg, default=0,
                   help=f"random seed of the simulation, 0 .. {MAX_SEED} (default 0)")
    p.add_argument("--out", type=out_dir_arg, default=Path("demo_out"),
                   help="report folder (default demo_out; an earlier run's report there is "
                        "moved aside to OUT.previous-N)")
    p.add_argument("--no-video", action="store_true", help="skip the MP4")
    p.add_argument("--fault", action="append", default=[], metavar="FAULT",
                   help=f"inject a fault mid-segment ({', '.join(FAULTS)}); repeat or "
                        "comma-separate to combine (default: none)")
    p.add_argument("--segments", type=segments_arg, default="abcdef",
                   help="which segments, each letter of abcdef at most once (default abcdef)")
    p.add_argument("--tracker", choices=TRACKERS, default="anchored",
                   help="feature-point tracker (default anchored: EAKF-STC fused with TIPM)")
    p.add_argument("--length-mm", type=float, default=None,
                   help="weld only this much of each segment (quick runs; default: the whole "
                        "segment)")
    p.add_argument("--model", type=model_arg, default=None, metavar="FILE",
                   help="tracker model file for the anchored and eakf-stc trackers, e.g. a "
                        "run's runs/NAME/live_tracker.safetensors (default "
                        "models/live_tracker.safetensors)")
    p.add_argument("--start-offset-mm", type=float, default=0.0, metavar="D",
                   help="start each segment D mm across the seam (the torch frame's y, at the "
                        "search stand-off of configs/search.yaml); the torch then searches for "
                        "the seam, arc off, within the search bound (35 mm / 20 deg); a seam not "
                        "found: the segment is incomplete, exit 1; default 0")
    p.add_argument("--start-angle-deg", type=float, default=0.0, metavar="A",
                   help="start each segment turned A degrees about the torch axis (searches "
                        "as --start-offset-mm); default 0")
    p.set_defaults(func=run)

    r = sub.add_parser(
        "replay",
        help="feed recorded frames (folder, video or camera) through the live loop, open loop",
        description="Open-loop replay: feed a recorded frame folder (dataset format) or a video "
                    "file through the same live loop the demo runs (tracking, triangulation, "
                    "ECAL, IPI plan) and print the per-stage latency and, with labels.csv, the "
                    "pixel error. Nothing is sent to a robot. Torch poses come from the "
                    "folder's meta.json when it has them; otherwise --pose (default: the "
                    "flange at the base origin, so 3D points are in the flange frame).")
    r.add_argument("source", help="frame folder (00000.png ...), video file, or a live "
                                  "camera: camera:N (device index) or a stream URL")
    r.add_argument("--tracker", choices=TRACKERS, default="anchored",
                   help="feature-point tracker (default anchored)")
    r.add_argument("--joint", choices=JOINT_PROFILES, default=None,
                   help="the joint in the frames (default: the part's joint a frame folder's "
                        "meta.json names, as `torchseam simulate` writes it, else fillet; "
                        "fillet: TIPM's corner, followed by --tracker; v_groove, butt, lap: the "
                        "profile's aim point, configs/profiles.yaml, with the default tracker)")
    r.add_argument("--init", default=None, metavar="U,V",
                   help="start pixel (default: TIPM on the first frame, which must be arc-off; "
                        "a --joint other than fillet: its profile's aim point there)")
    r.add_argument("--pose", default=None, metavar="X,Y,Z,Q1,Q2,Q3,Q4",
                   help="torch pose for frames without one (mm, quaternion w,x,y,z; default: "
                        "the tool pose with the flange at the base origin, so such frames' 3D "
                        "points are located in the flange frame)")
    r.add_argument("--fps", type=float, default=None,
                   help="frame rate for time stamps the source lacks (default: the file's, "
                        "else 25)")
    r.add_argument("--max-frames", type=int, default=None,
                   help="stop after N frames (default: all)")
    r.add_argument("--out", type=out_file_arg, default=None,
                   help="CSV of frame,t_s,u,v,status,x,y,z per frame (default: none)")
    r.add_argument("--model", type=model_arg, default=None, metavar="FILE",
                   help="tracker model file for the anchored and eakf-stc trackers, e.g. a "
                        "run's runs/NAME/live_tracker.safetensors (default "
                        "models/live_tracker.safetensors)")
    r.set_defaults(func=run_replay_cmd)


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise TorchseamError(f"{what} {text!r}: expected {n} comma-separated numbers") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise TorchseamError(f"{what} {text!r}: expected {n} finite comma-separated numbers")
    return vals


def run_replay_cmd(args: argparse.Namespace) -> int:
    import cv2  # here, not at the top: the parser (--help) needs no OpenCV or torch
    import numpy as np
    import torch

    from torchseam.core.transforms import pose_matrix
    from torchseam.live.events import DemoControl
    from torchseam.live.parts import load_live_parts
    from torchseam.live.replay import run_replay
    from torchseam.live.sources import FolderSource, open_source

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    if args.max_frames is not None and args.max_frames < 2:
        raise TorchseamError(f"--max-frames must be >= 2, got {args.max_frames}")
    if args.fps is not None and not args.fps > 0:
        raise TorchseamError(f"--fps must be > 0, got {args.fps}")
    uv0 = np.array(_floats(args.init, 2, "--init")) if args.init else None
    pose = None
    if args.pose:
        v = _floats(args.pose, 7, "--pose")
        q = np.array(v[3:])
        norm = float(np.linalg.norm(q))
        if not abs(norm - 1.0) <= NORM_TOLERANCE:  # as `robot ik` and a pose file: no guess
            raise TorchseamError(f"--pose: quaternion Q1..Q4 (w, x, y, z) must have norm 1, "
                                 f"got {norm:.6f}")
        pose = pose_matrix(np.array(v[:3]), q / norm)
    cell, parts = load_cell(), load_live_parts()
    # refused before any frame; without --joint, a frame folder's meta.json may name it
    given = args.joint
    tracker = parts.tracker(args.tracker, given, args.model) if given is not None else None
    source = open_source(args.source, (cell.camera.width, cell.camera.height), args.fps)
    ds = source.ds if isinstance(source, FolderSource) else None
    args.joint, origin, warning = ds.joint(given) if ds is not None else (given or "fillet",
                                                                          "", "")
    if warning:
        print(warning, file=sys.stderr, flush=True)
    if tracker is None:
        with contextlib.ExitStack() as undo:
            undo.enter_context(source)  # closed if the tracker is refused
            tracker = parts.tracker(args.tracker, args.joint, args.model)
            undo.pop_all()
    truth = None
    meta = source.ds.meta if isinstance(source, FolderSource) else None
    if meta and isinstance(meta.get("frames"), list):
        truth = {int(e["frame"]): np.asarray(e["seam_mm"], float)
                 for e in meta["frames"] if "seam_mm" in e and "frame" in e}
    # SIGINT / SIGTERM: the first stops the replay before the next frame (the figures and
    # --out then cover the frames done); a second quits at once
    control = DemoControl()
    stop = SignalStop(control.stop)
    t0 = time.perf_counter()
    with source, stop.installed():
        res = run_replay(cell, source,
                         tracker,
                         pose, uv0, parts=parts, max_frames=args.max_frames, truth=truth,
                         control=control)
    wall = time.perf_counter() - t0
    n = len(res.index)
    if stop.signal is not None and n == 0:
        print(f"torchseam replay: interrupted by {stop.signal} before the start frame was "
              "tracked: nothing to report", file=sys.stderr)
        return EXIT_SIGNAL[stop.signal]
    print(f"replay of {args.source}: {n + 1} frames (start frame {res.start_index}), tracker "
          f"{args.tracker}" + (f", joint {args.joint} (from {origin})" if origin else "")
          + f", {wall:.1f} s; torch poses "
          + ("from the recording" if res.poses_known else
             ("from --pose" if pose is not None else "not recorded: flange at the base origin "
              "(3D points in the flange frame)")))
    print(format_table(["figure", "value", "unit"], _replay_rows(res)))
    for m in res.messages[:8]:
        print("  " + m)
    if args.out is not None:
        _write_replay_csv(res, args.out)
        print(f"per-frame track: {args.out}")
    if stop.signal is not None:
        print(f"torchseam replay: interrupted by {stop.signal} after {n + 1} frames (start frame "
              "included): the figures above are theirs", file=sys.stderr)
        return EXIT_SIGNAL[stop.signal]
    return 0


def _replay_rows(res: Any) -> list[list[object]]:
    """The replay's figure table: tracked / lost, located, planned, errors, latencies."""
    import numpy as np

    from torchseam.track.fusion import TrackStatus

    n = len(res.index)
    lost = int(np.sum(res.status == int(TrackStatus.LOST)))
    located = int(np.sum(np.isfinite(res.p).all(axis=1)))
    rows: list[list[object]] = [["frames tracked / lost", f"{n - lost} / {lost}", ""],
            ["3D seam points located", located, ""],
            ["poses planned (open loop, not sent)", len(res.commands), ""]]
    err = res.pixel_errors()
    if len(err):
        rows += [["feature point vs label, RMSE", float(np.sqrt(np.mean(err**2))), "px"],
                 ["feature point vs label, max", float(err.max()), "px"],
                 ["frames > 5 px off", f"{100.0 * np.mean(err > 5):.1f} %", ""]]
    d = np.linalg.norm(res.p - res.p_true, axis=1)
    d = d[np.isfinite(d)]
    if len(d):
        rows.append(["located 3D seam point, RMSE", float(np.sqrt(np.mean(d**2))), "mm"])
    for k, (a, b) in res.latency.items():
        rows.append([f"{k} p50 / p99", f"{a:.2f} / {b:.2f}", "ms"])
    rows.append(["read a frame (source, not in the loop) p50 / p99",
                 f"{res.read_ms[0]:.2f} / {res.read_ms[1]:.2f}", "ms"])
    return rows


def _write_replay_csv(res: Any, path: Path) -> None:
    """``frame,t_s,u,v,status,x,y,z`` per frame after the start frame."""
    from torchseam.track.peers import STATUS_NAMES

    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as fh:
        fh.write("frame,t_s,u,v,status,x,y,z\n")
        for i in range(len(res.index)):
            u, v = res.uv[i]
            x, y, z = res.p[i]
            fh.write(f"{res.index[i]},{res.t_s[i]:.6f},{u:.4f},{v:.4f},"
                     f"{STATUS_NAMES.get(int(res.status[i]), res.status[i])},"
                     f"{x:.4f},{y:.4f},{z:.4f}\n")


# what --start-offset-mm / --start-angle-deg accept (bad input beyond: exit 2); the search's
# own bound (configs/search.yaml) is smaller: a start beyond it is a search that fails (exit 1)
MAX_START_OFFSET_MM = 100.0
MAX_START_ANGLE_DEG = 45.0


#: ``torchseam demo``'s exit codes: every segment welded; a segment not welded (its end not
#: reached, or a gap in its bead); bad input or a part the robot cannot weld; the report could
#: not be written (a full disk, a permission); SIGINT / SIGTERM: :data:`EXIT_SIGNAL` (128 + the
#: signal's number)
EXIT_OK, EXIT_INCOMPLETE, EXIT_BAD_INPUT, EXIT_REPORT = 0, 1, 2, 3


def demo_exit_code(summary: dict) -> int:
    """``torchseam demo``'s exit code from its summary: 130 / 143 when a signal interrupted it
    (``summary["interrupted"]``), else 1 when a segment was not welded
    (``summary["segments_incomplete"]``: its end not reached, or a gap in its bead), else
    0."""
    if summary.get("interrupted"):
        return EXIT_SIGNAL.get(summary["interrupted"], EXIT_INCOMPLETE)
    return EXIT_INCOMPLETE if summary.get("segments_incomplete") else EXIT_OK


def _report_failed(e: ReportError) -> int:
    print(f"torchseam demo: error: {e}", file=sys.stderr)
    return EXIT_REPORT


def _expected_frames(cell, part, plan, args: argparse.Namespace) -> int:
    """Frames the weld should take: approach + segment length at weld speed (the bar's 100 %;
    ``plan``: the planning settings)."""
    from torchseam.sim.scene import Scene

    seg_len = Scene(part).seam_length_mm / 6.0
    if args.length_mm is not None:
        seg_len = min(seg_len, args.length_mm)
    approach = cell.process.look_ahead_mm + plan.approach_mm
    per_seg = (approach + seg_len) / cell.process.weld_speed_mm_s * cell.process.frame_rate_hz
    return int(per_seg * len(args.segments))


def _demo_faults(args: argparse.Namespace) -> tuple[str, ...]:
    """The faults ``demo`` injects, its options checked first (one-line errors)."""
    faults = tuple(f.strip() for a in args.fault for f in a.split(",") if f.strip())
    bad = [f for f in faults if f not in FAULTS]
    if bad:
        raise TorchseamError(f"--fault {bad[0]!r}: use one of {', '.join(FAULTS)}")
    if args.length_mm is not None and not args.length_mm > 0:
        raise TorchseamError(f"--length-mm must be > 0, got {args.length_mm}")
    for name, v, most in (("--start-offset-mm", args.start_offset_mm, MAX_START_OFFSET_MM),
                          ("--start-angle-deg", args.start_angle_deg, MAX_START_ANGLE_DEG)):
        if not math.isfinite(v) or abs(v) > most:
            raise TorchseamError(f"{name} must be within +-{most:g}, got {v}")
    if not args.segments or set(args.segments) - set("abcdef"):
        raise TorchseamError(f"--segments {args.segments!r}: use letters from abcdef")
    return faults


def run(args: argparse.Namespace) -> int:
    """``torchseam demo``: :func:`_demo`, with the cyclic garbage collector off while the
    imports and the plan are made: their objects outlive the weld, so they are frozen out of
    the collector before it (as the EGM session's child does) instead of being gone over by
    its full passes, during the imports and after."""
    gc_on = gc.isenabled()
    gc.disable()
    try:
        return _demo(args, gc_on)
    finally:
        if gc_on:
            gc.enable()


def _demo(args: argparse.Namespace, gc_on: bool) -> int:
    import cv2  # here, not at the top: the parser (--help) needs no OpenCV or torch
    import torch
    from tqdm import tqdm

    from torchseam.core.report import prepare_out_dir, write_run_marker
    from torchseam.live.demo import DemoControl, run_demo, write_report
    from torchseam.live.parts import load_live_parts

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    faults = _demo_faults(args)
    parts = load_live_parts()
    if args.model is not None:
        from torchseam.track.peers import make_tracker

        make_tracker(args.tracker, parts.tipm, model_path=args.model)  # a bad file is refused
        # here, not after the pre-flight and the first segment's approach
    cell, part, noise = load_cell(), load_part(args.part), load_noise()
    try:
        level = noise.level(args.noise)
    except ValueError as e:
        raise TorchseamError(f"--noise: {e}") from None
    # the weld plan, every pose through the reachability gate, before anything moves
    from torchseam.live.demo import PlanRefused
    from torchseam.plan.preflight import preflight

    report = preflight(cell, part, config=parts.plan, robot=parts.robot,
                       part_name=str(args.part or "configs/parts/t_joint.yaml"))
    print(report.text(), flush=True)
    if not report.ok:
        print(f"torchseam demo: error: {PlanRefused(report).summary_line()}", file=sys.stderr)
        return 2
    # the run's own folder (an earlier report moved aside), marked RUNNING until its
    # summary.json is written
    control = DemoControl()
    # SIGINT / SIGTERM: the first stops the weld at the next frame (the report of what was
    # done is then written, marked interrupted); a second quits at once, leaving the folder
    # with its RUNNING marker and no summary.json
    stop = SignalStop(control.stop)
    with stop.installed():
        try:
            out = prepare_out_dir(args.out, "torchseam demo")
            write_run_marker(out, "torchseam demo")
        except ReportError as e:
            return _report_failed(e)
        video = None
        if not args.no_video:
            size = (cell.camera.width // 2, cell.camera.height // 2)  # half size: small
            video = cv2.VideoWriter(str(out / "weld.mp4"), cv2.VideoWriter.fourcc(*"mp4v"),
                                    cell.process.frame_rate_hz, size)
            if not video.isOpened():
                raise TorchseamError(f"{out / 'weld.mp4'}: OpenCV cannot write MP4 here "
                                     "(use --no-video)")
        gc.freeze()   # (see run)
        if gc_on:
            gc.enable()
        t0 = time.perf_counter()
        bar = tqdm(desc="weld", unit="frame",
                   total=_expected_frames(cell, part, parts.plan, args), mininterval=0.5)
        try:
            res = run_demo(cell, part, noise, level, args.seed, faults, args.segments,
                           args.tracker, video, progress=bar.update, length_mm=args.length_mm,
                           control=control, model_path=args.model, report=report,
                           start_offset_mm=args.start_offset_mm,
                           start_angle_deg=args.start_angle_deg, parts=parts)
        finally:
            bar.close()
            if video is not None:
                video.release()
        res.summary.update(interrupted=stop.signal, noise=args.noise)
        try:
            files: list[Path] = write_report(res, out)
            failed = None
        except ReportError as e:
            files, failed = [], e
    _print_demo(res, args, report.part_name, level, faults, time.perf_counter() - t0, out,
                files if failed is None else None, video is not None)
    if failed is not None:
        return _report_failed(failed)
    if res.summary["interrupted"]:  # (a signal while the report was written: it is whole)
        print(f"torchseam demo: interrupted by {stop.signal}: the weld stopped at "
              f"t={res.frames[-1].t_s if res.frames else 0.0:.2f} s; report "
              f"{out / 'summary.json'} (interrupted)", file=sys.stderr)
    return demo_exit_code(res.summary)


def _print_demo(res: Any, args: argparse.Namespace, part_name: str, level: float,
                faults: tuple[str, ...], wall_s: float, out: Path, files: list[Path] | None,
                video: bool) -> None:
    """The demo's summary on stdout (``files``: the report written; None: it was not)."""
    s = res.summary
    print(f"\nclosed-loop weld of {part_name}: {len(args.segments)} segment(s), noise "
          f"{level:g}, seed {args.seed}, tracker {args.tracker}"
          + (f" (model {args.model})" if args.model is not None else "")
          + (f", faults {', '.join(faults)}" if faults else "")
          + f" ({wall_s:.0f} s)")
    print(format_table(
        ["figure", "value", "unit"],
        [["torch path vs true seam, RMSE", s["seam_rmse_mm"], "mm"],
         ["torch path vs true seam, max", s["seam_max_mm"], "mm"],
         ["nominal path vs true seam, RMSE", s["nominal_rmse_mm"], "mm"],
         ["nominal path vs true seam, max", s["nominal_max_mm"], "mm"],
         ["torch axis vs true bisector (arc on), RMSE / max",
          f"{s['axis_rmse_deg']:.2f} / {s['axis_max_deg']:.2f}", "deg"],
         ["torch axis within 1 degree (arc on)",
          f"{s['axis_within_1deg']} of {s['poses_welded']}", ""],
         ["located 3D seam point, RMSE", s["located_rmse_mm"], "mm"],
         ["feature point, RMSE", s["pixel_rmse_px"], "px"],
         ["frame -> command latency p50 / p99",
          f"{s['latency_p50_ms']:.2f} / {s['latency_p99_ms']:.2f}", "ms"],
         ["poses sent", s["poses_sent"], ""],
         ["poses refused", s["poses_refused"], ""],
         ["loop holds", s["holds"], ""],
         ["arc held off past the approach", s["arc_off_s"], "s"],
         ["unsafe poses sent (independent re-check)", s["unsafe_poses_sent"], ""]]))
    if s["refused_reasons"]:
        print("refused: " + ", ".join(f"{k} {v}" for k, v in s["refused_reasons"].items()))
    if s["hold_reasons"]:
        print("holds: " + ", ".join(f"{k} {v}" for k, v in s["hold_reasons"].items()))
    print("latency per stage (p50 / p99 ms): " + ", ".join(
        f"{k} {a:.2f}/{b:.2f}" for k, (a, b) in res.latency.items()))
    if any(g["arc_out_t_s"] is not None for g in s["arc_gaps"]):  # (not the strike alone)
        print("seam passed with the arc out (unwelded): " + ", ".join(
            f"segment {k} {v:.2f} mm" for k, v in s["unwelded_mm"].items()))
    for m in res.messages[:12]:
        print("  " + m)
    if len(res.messages) > 12:
        print(f"  ... {len(res.messages) - 12} more in {out / 'messages.txt'}")
    if files is not None:
        print(f"report: {', '.join(str(f) for f in files)}"
              + (f", {out / 'weld.mp4'}" if video else ""))
    for srch in s.get("search", []):
        print(f"segment {srch['segment']}: " + (
            f"seam found by the search in {srch['time_s']:.2f} s" if srch["found"]
            else srch["reason"]))
    for seg in s["segments_incomplete"]:
        print(f"segment {seg['segment']} NOT completed: {seg['reason']}")
