"""``torchseam demo``: the closed-loop weld of the simulated T joint, with a report folder."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import torch
from tqdm import tqdm

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.errors import TorchseamError
from torchseam.core.report import format_table
from torchseam.track.peers import TRACKERS


def register(sub: argparse._SubParsersAction) -> None:
    from torchseam.live.demo import FAULTS

    p = sub.add_parser(
        "demo", help="weld the simulated T joint in closed loop and write a report",
        description="Weld the whole 203/152 mm T joint in six segments in closed loop: the "
                    "simulator renders what the sensor sees from where the simulated robot is, "
                    "the live loop tracks (EAKF-STC), locates, plans and guides the simulated "
                    "IRB 1410 over EGM. Prints a summary table and writes plots, a video and "
                    "summary.json into --out.")
    p.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml)")
    p.add_argument("--noise", default="heavy", help="arc-noise level: name or 0..1 (heavy)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("demo_out"),
                   help="report folder (default demo_out)")
    p.add_argument("--no-video", action="store_true", help="skip the MP4")
    p.add_argument("--fault", action="append", default=[], metavar="FAULT",
                   help=f"inject a fault mid-segment ({', '.join(FAULTS)}); repeat or "
                        "comma-separate to combine")
    p.add_argument("--segments", default="abcdef", help="which segments (default abcdef)")
    p.add_argument("--tracker", choices=TRACKERS, default="anchored",
                   help="feature-point tracker (default anchored: EAKF-STC re-anchored by TIPM)")
    p.add_argument("--length-mm", type=float, default=None,
                   help="weld only this much of each segment (quick runs)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torchseam.live.demo import FAULTS, run_demo, write_report

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    faults = tuple(f.strip() for a in args.fault for f in a.split(",") if f.strip())
    bad = [f for f in faults if f not in FAULTS]
    if bad:
        raise TorchseamError(f"--fault {bad[0]!r}: use one of {', '.join(FAULTS)}")
    if args.length_mm is not None and not args.length_mm > 0:
        raise TorchseamError(f"--length-mm must be > 0, got {args.length_mm}")
    if not args.segments or set(args.segments) - set("abcdef"):
        raise TorchseamError(f"--segments {args.segments!r}: use letters from abcdef")
    cell, part, noise = load_cell(), load_part(args.part), load_noise()
    try:
        level = noise.level(args.noise)
    except ValueError as e:
        raise TorchseamError(f"--noise: {e}") from None
    args.out.mkdir(parents=True, exist_ok=True)
    video = None
    if not args.no_video:
        size = (cell.camera.width // 2, cell.camera.height // 2)  # half size keeps it small
        video = cv2.VideoWriter(str(args.out / "weld.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                                cell.process.frame_rate_hz, size)
        if not video.isOpened():
            raise TorchseamError(f"{args.out / 'weld.mp4'}: OpenCV cannot write MP4 here "
                                 "(use --no-video)")
    t0 = time.perf_counter()
    bar = tqdm(desc="weld", unit="frame", total=330 * len(args.segments), mininterval=0.5)
    try:
        res = run_demo(cell, part, noise, level, args.seed, faults, args.segments,
                       args.tracker, video, progress=bar.update, length_mm=args.length_mm)
    finally:
        bar.close()
        if video is not None:
            video.release()
    files = write_report(res, args.out)
    s = res.summary
    print(f"\nclosed-loop weld: {len(args.segments)} segment(s), noise {level:g}, seed "
          f"{args.seed}, tracker {args.tracker}"
          + (f", faults {', '.join(faults)}" if faults else "")
          + f" ({time.perf_counter() - t0:.0f} s)")
    print(format_table(
        ["figure", "value", "unit"],
        [["torch path vs true seam, RMSE", s["seam_rmse_mm"], "mm"],
         ["torch path vs true seam, max", s["seam_max_mm"], "mm"],
         ["nominal path vs true seam, RMSE", s["nominal_rmse_mm"], "mm"],
         ["nominal path vs true seam, max", s["nominal_max_mm"], "mm"],
         ["located 3D seam point, RMSE", s["located_rmse_mm"], "mm"],
         ["feature point, RMSE", s["pixel_rmse_px"], "px"],
         ["frame -> command latency p50 / p99",
          f"{s['latency_p50_ms']:.2f} / {s['latency_p99_ms']:.2f}", "ms"],
         ["poses sent", s["poses_sent"], ""],
         ["poses refused", s["poses_refused"], ""],
         ["unsafe poses sent (independent re-check)", s["unsafe_poses_sent"], ""]]))
    if s["refused_reasons"]:
        print("refused: " + ", ".join(f"{k} {v}" for k, v in s["refused_reasons"].items()))
    print("latency per stage (p50 / p99 ms): " + ", ".join(
        f"{k} {a:.2f}/{b:.2f}" for k, (a, b) in res.latency.items()))
    for m in res.messages[:12]:
        print("  " + m)
    if len(res.messages) > 12:
        print(f"  ... {len(res.messages) - 12} more in {args.out / 'messages.txt'}")
    print(f"report: {', '.join(str(f) for f in files)}"
          + (f", {args.out / 'weld.mp4'}" if video is not None else ""))
    return 0
