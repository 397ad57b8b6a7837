"""``torchseam calibrate``: the geometry stage's kinds (camera, laser, handeye, tcp, simulate)
and ``latency``, which needs the cell's camera and controller (the live stage)."""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import signal
import sys
from pathlib import Path

from torchseam.core.cliargs import number_arg
from torchseam.core.errors import TorchseamError
from torchseam.geometry import calib_cli

#: a fit whose median residual is above this (px) is not believed: the stripe's rows do not
#: follow the fed-back motion (a clean fit leaves about 0.1 px, the centre line's noise)
MAX_RESIDUAL_PX = 1.0


_positive = number_arg(0.0, lo_open=True)


def register(sub: argparse._SubParsersAction) -> None:
    kinds = calib_cli.register(sub)
    q = kinds.add_parser(
        "latency", help="the camera's latency against the controller's feedback",
        description="Measure the camera's latency (exposure -> arrival at this PC) against the "
                    "controller's fed-back motion and write it into the cell file "
                    "(camera.latency_ms): RAPID hands a motion over to EGM (its latency "
                    "routine; `torchseam virtual-cell --program latency`), the sensor moves "
                    "up and down along the torch axis over the part, and the stripe's motion "
                    "in the image is matched to the fed-back motion.")
    q.add_argument("--cell", type=Path, required=True,
                   help="the cell file to measure and update; waited for up to --wait-cell s "
                        "when it is not there yet (a virtual cell started just before)")
    q.add_argument("--wait-cell", type=_positive, default=60.0, metavar="S",
                   help="wait this long for a cell file that is not there yet (default 60)")
    q.add_argument("--duration", type=_positive, default=10.0, metavar="S",
                   help="how long the sensor moves (default 10 s)")
    q.add_argument("--amplitude-mm", type=_positive, default=2.0,
                   help="up and down by this much (default 2 mm)")
    q.add_argument("--period-s", type=_positive, default=2.0,
                   help="one up-and-down in this long (default 2 s)")
    q.add_argument("--dry-run", action="store_true",
                   help="measure and print, leave the cell file as it is")
    q.set_defaults(func=run_latency)


def run_latency(args: argparse.Namespace) -> int:
    import cv2
    import torch

    from torchseam.core.report import format_table
    from torchseam.live.cellfile import load_weld_cell, wait_for_cell, write_latency
    from torchseam.live.latency import measure_latency
    from torchseam.live.parts import load_live_parts
    from torchseam.live.weld import Interrupted, WeldRunner

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    wait_for_cell(args.cell, args.wait_cell, "calibrate latency")
    cell = load_weld_cell(args.cell)
    if 2 * math.pi * args.amplitude_mm / args.period_s > cell.calibration.process.weld_speed_mm_s:
        raise TorchseamError("--amplitude-mm / --period-s: the sine's top speed "
                             f"{2 * math.pi * args.amplitude_mm / args.period_s:.1f} mm/s is "
                             "above the weld speed (the controller's guided speed)")
    runner = WeldRunner(cell, None, load_live_parts(), "", None,
                        progress=lambda m: print(m, flush=True))
    old = {s: signal.signal(s, runner.on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        runner.open()
        res = measure_latency(runner, args.duration, args.amplitude_mm, args.period_s)
    except Interrupted as e:
        print(f"torchseam calibrate latency: interrupted by {e}: the motion aborted towards "
              f"RAPID, nothing measured, {args.cell} left as it is", file=sys.stderr)
        return 130 if str(e) == "SIGINT" else 143
    finally:
        if hasattr(runner, "link"):
            runner.close()
        for s, h in old.items():
            signal.signal(s, h)
    print(format_table(["figure", "value", "unit"], [
        ["camera latency (exposure -> arrival)", f"{res.latency_ms:.2f}", "ms"],
        ["in the cell file before", f"{cell.camera.latency_ms:.2f}", "ms"],
        ["fit: median absolute residual", f"{res.residual_px:.3f}", "px"],
        ["stripe motion per mm of height", f"{res.px_per_mm:.2f}", "px/mm"],
        ["frames", res.frames, ""]]))
    if res.residual_px > MAX_RESIDUAL_PX:
        print("torchseam calibrate latency: error: the fit does not hold (median residual "
              f"{res.residual_px:.2f} px > {MAX_RESIDUAL_PX:g}): the stripe did not follow the "
              "sensor's motion (frames lost, the robot held, the stripe off the part); the cell "
              "file is left as it is: run it again", file=sys.stderr)
        return 1
    if abs(res.px_per_mm) < 1.0:
        print("torchseam calibrate latency: error: the stripe hardly moved with the sensor "
              f"({res.px_per_mm:.2f} px/mm): is the stripe on the part?", file=sys.stderr)
        return 1
    if not args.dry_run:
        kept = write_latency(args.cell, cell, float(res.latency_ms),
                             f"calibrated: torchseam calibrate latency "
                             f"({_dt.date.today().isoformat()})")
        how = "" if kept else " (written anew, the file's comments not kept)"
        print(f"camera.latency_ms = {res.latency_ms:.2f} written to {args.cell}{how}")
    return 0
