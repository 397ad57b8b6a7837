"""``torchseam demo``: the main job on the built-in simulated T joint.

For now the demo simulates a short clean sequence, runs TIPM on every frame and prints the
accuracy and speed against the simulator's ground truth; the closed-loop weld grows here.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.errors import TorchseamError
from torchseam.core.report import error_stats, format_table, percentiles_ms
from torchseam.sim.sequence import SequenceSpec, simulate
from torchseam.vision.tipm import Tipm, draw_overlay


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="run the built-in simulated T joint and print the error table",
        description="Simulate the sensor along the default T joint, find the feature point in "
                    "every frame with TIPM and compare with the simulator's truth.")
    p.add_argument("--frames", type=int, default=120, help="frames to simulate (default 120)")
    p.add_argument("--noise", default="clean", help="arc-noise level name or number (clean)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml)")
    p.add_argument("--out", type=Path, help="write overlay frames of the run into this folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.frames < 1:
        raise TorchseamError(f"--frames must be at least 1, got {args.frames}")
    cv2.setNumThreads(1)
    cell, part, noise = load_cell(), load_part(args.part), load_noise()
    try:
        level = noise.level(args.noise)
    except ValueError as e:
        raise TorchseamError(f"--noise: {e}") from None
    tipm = Tipm()
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
    err, secs, reasons = [], [], {}
    frames = simulate(cell, part, noise, SequenceSpec(args.frames, level, args.seed))
    for img, truth in tqdm(frames, total=args.frames, desc="demo", unit="frame"):
        t0 = time.perf_counter()
        res = tipm(img)
        secs.append(time.perf_counter() - t0)
        err.append(np.linalg.norm(res.uv - truth.uv) if res.ok else np.nan)
        if not res.ok:
            reasons[res.reason] = reasons.get(res.reason, 0) + 1
        if args.out:
            cv2.imwrite(str(args.out / f"{truth.index:05d}.png"),
                        draw_overlay(img, res, truth.uv))
    s = error_stats(np.array(err))
    p50, p99 = percentiles_ms(secs)
    print(f"\nTIPM on the simulated T joint ({part.main_od_mm:g}/{part.branch_od_mm:g} mm, "
          f"noise level {level:g}, seed {args.seed})")
    print(format_table(
        ["frames", "found", "RMSE px", "max px", "> 5 px %", "ms p50", "ms p99"],
        [[s["n"], s["n"] - int(round(s["pct_none"] * s["n"] / 100)), s["rmse"], s["max"],
          s["pct_gt5"], p50, p99]]))
    for why, n in sorted(reasons.items(), key=lambda kv: -kv[1]):
        print(f"  no point in {n} frames: {why}")
    return 0
