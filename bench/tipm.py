"""TIPM speed and accuracy on simulated 656 x 492 frames, clean and under arc noise.

Usage: python bench/tipm.py [--sequences 4] [--frames 100] [--threads 1]

Prints one table: per noise level, how often TIPM gives a point, its error against the
simulator's truth (RMSE, max, % > 5 px, % lost > 15 px counting "no point" as lost), and the
time per full frame (median, p99) on one core (OpenCV threads set by --threads).
"""

from __future__ import annotations

import argparse
import platform
import time

import cv2
import numpy as np
import torch

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.report import error_stats, format_table, percentiles_ms
from torchseam.sim.sequence import SequenceSpec, simulate
from torchseam.vision.tipm import load_tipm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    ap.add_argument("--levels", default="clean,light,strike,heavy")
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    torch.set_num_threads(1)  # the renderer's threads must not spin beside the timed calls
    cell, part, noise = load_cell(), load_part(), load_noise()
    rows = []
    for name in args.levels.split(","):
        level = noise.level(name)
        for method in ("subpixel", "thinning"):
            tipm = load_tipm(centre_line=method)
            err, secs = [], []
            for seed in range(args.sequences):
                spec = SequenceSpec(n_frames=args.frames, level=level, seed=100 + seed)
                # render first, then time: frames arrive from a camera, and the renderer's
                # torch threads must not share the core with the timed call
                seq = list(simulate(cell, part, noise, spec))
                for k, (img, truth) in enumerate(seq):
                    if level > 0 and k < noise.clean_lead_frames:
                        continue  # arc-off lead frames are not arc frames
                    t0 = time.perf_counter()
                    res = tipm(img)
                    secs.append(time.perf_counter() - t0)
                    err.append(np.linalg.norm(res.uv - truth.uv) if res.ok else np.nan)
            s = error_stats(np.array(err))
            p50, p99 = percentiles_ms(secs)
            rows.append([name, method, s["n"], 100 - s["pct_none"], s["rmse"], s["max"],
                         s["pct_gt5"], s["pct_lost"], p50, p99])
    cpu = platform.processor() or platform.machine()
    print(f"TIPM on {cell.camera.width} x {cell.camera.height} frames; {cpu}, OpenCV threads "
          f"{args.threads}; {args.sequences} sequences x {args.frames} frames per level")
    print(format_table(["noise", "centre line", "frames", "point %", "RMSE px", "max px",
                        ">5px %", "lost %", "ms p50", "ms p99"], rows))
    print("Errors over frames with a point; 'lost' counts frames with no point or > 15 px off.")


if __name__ == "__main__":
    main()
