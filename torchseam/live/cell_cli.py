"""``torchseam weld`` (a real cell, or the virtual one) and ``torchseam virtual-cell``."""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from pathlib import Path
from typing import Any

from torchseam.core.cliargs import (
    MAX_SEED,
    model_arg,
    number_arg,
    out_dir_arg,
    out_file_arg,
    seed_arg,
    segments_arg,
)
from torchseam.core.config import MAX_NOISE_LEVEL
from torchseam.core.errors import TorchseamError
from torchseam.track.names import TRACKERS

#: the faults ``torchseam virtual-cell --fault`` injects (torchseam.live.virtual_cell)
VIRTUAL_FAULTS = ("camera-stall", "camera-drop", "packet-loss", "controller-restart")


_length = number_arg(0.0, lo_open=True, what="a length in mm")
_ms = number_arg(0.0, 1000.0, what="milliseconds")
_offset = number_arg(-1e9, 1e9, what="seconds")


def _faults(text: str) -> list[str]:
    out = [f.strip() for f in text.split(",") if f.strip()]
    bad = [f for f in out if f not in VIRTUAL_FAULTS]
    if bad or not out:
        raise argparse.ArgumentTypeError(f"{text!r}: use one of {', '.join(VIRTUAL_FAULTS)}")
    return out


def register(sub: argparse._SubParsersAction) -> None:
    w = sub.add_parser(
        "weld", help="weld a cell: camera frames and the controller's EGM in, poses and the "
                     "arc out",
        description="Weld a real cell (or `torchseam virtual-cell`) through its interfaces: "
                    "the camera's frame stream and the controller's EGM (RAPID data channel: "
                    "RobotWare 6.10 or later; `torchseam robot rapid` prints the RAPID module "
                    "that runs the segments). The pre-flight plan first (exit 2 when the robot "
                    "cannot weld the part); then per segment RAPID brings the torch to its "
                    "start and hands over to EGM, the weld tracks, guides and asks for the arc, "
                    "and says when the segment is done. Writes OUT/summary.json (no truth: a "
                    "cell has none). Exit 0 only when every asked segment was welded; 1 with "
                    "the reasons otherwise; 130 / 143 on SIGINT / SIGTERM (arc off, robot "
                    "held, report marked interrupted); 2 on bad input.")
    w.add_argument("--cell", type=Path, required=True,
                   help="cell file: calibration, camera source, controller address "
                        "(`torchseam virtual-cell --write-cell` writes one); waited for up to "
                        "--wait-cell s when it is not there yet")
    w.add_argument("--part", type=Path, required=True, help="part config (configs/parts/)")
    w.add_argument("--segments", type=segments_arg, default="abcdef",
                   help="which segments, letters of abcdef (default abcdef)")
    w.add_argument("--length-mm", type=_length, default=None,
                   help="weld only this much of each segment (default: all of it)")
    w.add_argument("--out", type=out_dir_arg, default=Path("weld_out"),
                   help="report folder (default weld_out; an earlier run's report there is "
                        "moved aside to OUT.previous-N, said on stderr)")
    w.add_argument("--tracker", choices=TRACKERS, default="anchored",
                   help="feature-point tracker (default anchored)")
    w.add_argument("--model", type=model_arg, default=None, metavar="FILE",
                   help="tracker model file (default models/live_tracker.safetensors)")
    w.add_argument("--wait-cell", type=float, default=60.0, metavar="S",
                   help="wait this long for a cell file that is not there yet (default 60)")
    w.add_argument("--connect-timeout", type=float, default=60.0, metavar="S",
                   help="wait this long for the camera and the controller (default 60)")
    w.set_defaults(func=run_weld_cmd)

    v = sub.add_parser(
        "virtual-cell", help="a simulated IRC5 and laser camera in their own processes",
        description="A virtual weld cell for `torchseam weld`: a simulated IRC5 (EGM over UDP "
                    "at 4 ms with its own clock, the RAPID data channel, RAPID's segment "
                    "sequence, EGM's communication timeout) and a laser camera (frames "
                    "rendered from the robot's actual pose at each exposure time, delivered "
                    "after the set latency over a frame stream), in processes of their own. "
                    "Ends when RAPID's program ends and writes OUT/summary.json from the "
                    "truth: the executed torch path against the true seam.")
    v.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml)")
    v.add_argument("--segments", type=segments_arg, default="abcdef",
                   help="RAPID's program: which segments (default abcdef)")
    v.add_argument("--length-mm", type=_length, default=None,
                   help="the length of each segment the truth checks (default: all of it)")
    v.add_argument("--noise", default="strike",
                   help="arc-noise level: a name from configs/noise.yaml or a number in "
                        f"[0, {MAX_NOISE_LEVEL:g}] (default strike)")
    v.add_argument("--seed", type=seed_arg, default=0,
                   help=f"random seed of the simulation, 0 .. {MAX_SEED} (default 0)")
    v.add_argument("--camera-latency-ms", type=_ms, default=20.0,
                   help="exposure -> delivery of each frame, ms (default 20)")
    v.add_argument("--clock-offset-s", type=_offset, default=0.0,
                   help="the controller's clock minus the PC's, s (default 0)")
    v.add_argument("--comm-timeout-s", type=float, default=0.5,
                   help="EGM's communication timeout: no reply this long stops the robot and "
                        "ends the program (default 0.5)")
    v.add_argument("--arc-hold-ms", type=float, default=100.0,
                   help="the arc goes out when the sensor's data is older than this (default "
                        "100)")
    v.add_argument("--wait-sensor-s", type=float, default=120.0,
                   help="how long RAPID waits for the sensor before the program ends "
                        "(default 120)")
    v.add_argument("--fault", type=_faults, action="extend", default=[], metavar="FAULT",
                   help=f"inject a fault mid-segment ({', '.join(VIRTUAL_FAULTS)}); "
                        "comma-separate or repeat")
    v.add_argument("--rapid-data", choices=("on", "off"), default="on",
                   help="off: a controller on the older EGM schema (RobotWare before 6.10): no "
                        "RAPID data channel; RAPID switches the arc itself and takes back when "
                        "EGM converged (default on)")
    v.add_argument("--program", choices=("weld", "latency"), default="weld",
                   help="RAPID's program: the weld's segments, or the latency calibration's "
                        "motion over segment a's start (`torchseam calibrate latency`)")
    v.add_argument("--out", type=out_dir_arg, default=Path("virtual_cell_out"),
                   help="report folder (default virtual_cell_out)")
    v.add_argument("--write-cell", type=out_file_arg, default=None, metavar="FILE",
                   help="write the cell file `torchseam weld --cell` reads (camera source, "
                        "controller address, the virtual camera's calibration)")
    v.set_defaults(func=run_virtual_cell_cmd)


def run_virtual_cell_cmd(args: argparse.Namespace) -> int:
    from torchseam.live.virtual_cell import run_virtual_cell

    for name, val in (("--comm-timeout-s", args.comm_timeout_s),
                      ("--arc-hold-ms", args.arc_hold_ms),
                      ("--wait-sensor-s", args.wait_sensor_s)):
        if not (math.isfinite(val) and val > 0):
            raise TorchseamError(f"{name} must be > 0, got {val}")
    if args.part is None:
        from torchseam.core.config import config_path

        args.part = config_path("parts", "t_joint.yaml")
    return run_virtual_cell(args)


def run_weld_cmd(args: argparse.Namespace) -> int:
    import cv2
    import torch

    from torchseam.core.config import load_part
    from torchseam.core.report import format_table, prepare_out_dir, write_json_atomic
    from torchseam.live.cellfile import load_weld_cell, wait_for_cell
    from torchseam.live.parts import load_live_parts
    from torchseam.live.weld import WeldRunner, exit_code, weld_summary, write_weld_files
    from torchseam.plan.preflight import preflight

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    wait_for_cell(args.cell, args.wait_cell, "weld")
    cell = load_weld_cell(args.cell)
    part = load_part(args.part)
    parts = load_live_parts()
    # the part's joint decides what is tracked (a fillet: --tracker; else its profile): a
    # tracker that cannot follow it, or a bad model file, is refused now
    parts.tracker(args.tracker, part.joint, args.model)
    report = preflight(cell.calibration, part, config=parts.plan, robot=parts.robot,
                       part_name=str(args.part))
    print(report.text(), flush=True)
    if not report.ok:
        print(f"torchseam weld: error: the robot cannot weld {report.part_name}: pre-flight "
              f"refused segment(s) {', '.join(report.refused)}; nothing moved", file=sys.stderr)
        return 2
    out = prepare_out_dir(args.out, "torchseam weld")
    (out / "RUNNING").write_text("the weld is running; summary.json is written at its end\n")
    runner = WeldRunner(cell, report, parts, args.segments, args.length_mm,
                        tracker=args.tracker, model_path=args.model,
                        progress=lambda m: print(m, flush=True),
                        connect_timeout_s=args.connect_timeout)
    old = {s: signal.signal(s, runner.on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    t0 = time.monotonic()
    try:
        res = runner.run()
    except TorchseamError as e:
        # the cell could not be reached, or broke its protocol: the report says so too
        write_json_atomic(out / "summary.json", {
            "part": str(args.part), "cell": str(args.cell), "segments": args.segments,
            "segments_welded": [], "error": str(e),
            "segments_incomplete": [{"segment": n, "reason": str(e)} for n in args.segments]})
        (out / "RUNNING").unlink(missing_ok=True)
        raise
    except Exception as e:
        # a fault of this program (a bug): the arc went out and RAPID was told (WeldRunner.run);
        # the report says so, the traceback goes to a file, one line on the terminal
        import traceback

        (out / "error.txt").write_text(traceback.format_exc())
        why = f"internal error: {type(e).__name__}: {e} (traceback in {out / 'error.txt'})"
        write_json_atomic(out / "summary.json", {
            "part": str(args.part), "cell": str(args.cell), "segments": args.segments,
            "segments_welded": [], "error": why,
            "segments_incomplete": [{"segment": n, "reason": why} for n in args.segments]})
        (out / "RUNNING").unlink(missing_ok=True)
        print(f"torchseam weld: {why}; nothing claimed welded", file=sys.stderr)
        return 1
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    info = {"part": str(args.part), "cell": str(args.cell), "segments": args.segments,
            "length_mm": args.length_mm, "tracker": args.tracker,
            "model": str(args.model) if args.model else "models/live_tracker.safetensors",
            "wall_s": round(time.monotonic() - t0, 2)}
    summary = weld_summary(res, info)
    write_weld_files(res, out)
    write_json_atomic(out / "summary.json", summary)     # last: the run's word
    (out / "RUNNING").unlink(missing_ok=True)
    sm = summary
    print(format_table(["figure", "value", "unit"], summary_rows(sm, args.segments)))
    for seg in sm["segments_incomplete"]:
        print(f"segment {seg['segment']} NOT welded: {seg['reason']}")
    if res.interrupted:
        print(f"torchseam weld: interrupted by {res.interrupted}: arc off, robot held; report "
              f"{out / 'summary.json'} (interrupted)", file=sys.stderr)
    print(f"report: {out / 'summary.json'}")
    return exit_code(res)


def summary_rows(sm: dict[str, Any], segments: str) -> list[list[Any]]:
    """The table ``torchseam weld`` ends with, from its summary.json ``sm`` (the ``segments``
    asked for)."""
    lat = ("n/a" if sm["latency_p50_ms"] is None
           else f"{sm['latency_p50_ms']:.2f} / {sm['latency_p99_ms']:.2f}")
    link = sm.get("link") or {}            # empty where the weld ended before the link ran
    offset = (sm.get("clocks") or {}).get("controller_offset_s")
    rows = [
        ["segments welded", f"{len(sm['segments_welded'])} of {len(segments)}", ""],
        ["frames / without a pose / dropped", f"{sm['frames']} / {sm['frames_without_pose']} / "
                                              f"{sm['frames_dropped_by_weld']}", ""],
        ["camera stalls", sm["camera_stalls"], ""],
        ["frame -> command latency p50 / p99", lat, "ms"],
        ["EGM replies sent / late", f"{link['sent']} / {link['late_replies']}"
         if "sent" in link else "n/a", ""],
        ["controller clock offset", f"{offset:+.4f}" if offset is not None else "n/a", "s"],
        ["loop holds", sum(sm["holds"].values()), ""]]
    ae = sm.get("exposure")
    if ae is not None:
        rows.append(["automatic exposure min / median / max (changes)",
                     f"{ae['scale_min']:.2f} / {ae['scale_median']:.2f} / "
                     f"{ae['scale_max']:.2f} ({ae['changes']})", "x"])
    return rows

