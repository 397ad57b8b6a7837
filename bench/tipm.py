"""TIPM speed and accuracy on simulated 656 x 492 frames, clean and under arc noise.

Usage: python bench/tipm.py [--families sim] [--sequences 4] [--frames 100] [--threads 1]

Prints one table: per appearance family and noise level, how often TIPM gives a point, its
error against the simulator's truth (RMSE, max, % > 5 px, % lost > 15 px counting "no point"
as lost), the mean error (u, v): the part of it that is one constant offset, and the RMSE
about that mean, and the time per full frame (median, p99) on one core (OpenCV threads set by
--threads). Each sequence is read in the view (stripe axis, colour response) found on its first
frame, as the live loop reads a stream.
"""

from __future__ import annotations

import argparse
import platform
import time

import cv2
import numpy as np
import torch

from torchseam.core.config import FAMILY_NAMES, load_cell, load_noise, load_part
from torchseam.core.report import error_stats, format_table, percentiles_ms
from torchseam.sim.sequence import SequenceSpec, simulate
from torchseam.vision.tipm import find_view, load_tipm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default="sim",
                    help="appearance families, comma-separated, or all (default sim)")
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    ap.add_argument("--levels", default="clean,light,strike,heavy",
                    help="noise levels, comma-separated (default clean,light,strike,heavy)")
    ap.add_argument("--methods", default="subpixel,thinning",
                    help="centre lines, comma-separated (default subpixel,thinning)")
    args = ap.parse_args()
    families = list(FAMILY_NAMES) if args.families == "all" else args.families.split(",")
    for f in families:
        if f not in FAMILY_NAMES:
            ap.error(f"--families: unknown family {f!r} (use {', '.join(FAMILY_NAMES)} or all)")
    cv2.setNumThreads(args.threads)
    torch.set_num_threads(1)  # the renderer's threads must not spin beside the timed calls
    cell, part, noise = load_cell(), load_part(), load_noise()
    for name in args.levels.split(","):
        try:
            noise.level(name)
        except ValueError as e:
            ap.error(f"--levels: {e}")
    rows = []
    for fam in families:
        for name in args.levels.split(","):
            level = noise.level(name)
            for method in args.methods.split(","):
                rows.append([fam, name, method, *measure(cell, part, noise, fam, level, method,
                                                          args.sequences, args.frames)])
    cpu = platform.processor() or platform.machine()
    print(f"TIPM on {cell.camera.width} x {cell.camera.height} frames; {cpu}, OpenCV threads "
          f"{args.threads}; {args.sequences} sequences x {args.frames} frames per level")
    print(format_table(["family", "noise", "centre line", "frames", "point %", "RMSE px",
                        "max px", ">5px %", "lost %", "mean du", "mean dv", "RMSE-mean",
                        "ms p50", "ms p99"], rows))
    print("Errors over frames with a point; 'lost' counts frames with no point or > 15 px off; "
          "mean du, dv: the mean error (px), RMSE-mean: the RMSE about it.")


def measure(cell, part, noise, family: str, level: float, method: str, sequences: int,
            frames: int) -> list:
    """One row's figures: TIPM with ``method`` on ``sequences`` x ``frames`` of ``family``."""
    tipm = load_tipm(centre_line=method)
    err, d, secs = [], [], []
    for seed in range(sequences):
        spec = SequenceSpec(n_frames=frames, level=level, seed=100 + seed, family=family)
        # render first, then time: frames arrive from a camera, and the renderer's torch
        # threads must not share the core with the timed call
        seq = list(simulate(cell, part, noise, spec))
        view = find_view(seq[0][0], tipm)
        if view is None:
            raise SystemExit(f"{family} seed {100 + seed}: no corner on the first frame")
        for k, (img, truth) in enumerate(seq):
            if level > 0 and k < noise.clean_lead_frames:
                continue  # arc-off lead frames are not arc frames
            t0 = time.perf_counter()
            res = tipm(view.frame(img))
            secs.append(time.perf_counter() - t0)
            if res.ok:
                e = view.to_camera(res.uv) - truth.uv
                err.append(float(np.linalg.norm(e)))
                d.append(e)
            else:
                err.append(np.nan)
    s = error_stats(np.array(err))
    p50, p99 = percentiles_ms(secs)
    dd = np.array(d).reshape(-1, 2)
    mean = dd.mean(axis=0) if len(dd) else np.full(2, np.nan)
    about = float(np.sqrt(np.mean(np.sum((dd - mean) ** 2, axis=1)))) if len(dd) else np.nan
    return [s["n"], 100 - s["pct_none"], s["rmse"], s["max"], s["pct_gt5"], s["pct_lost"],
            float(mean[0]), float(mean[1]), about, p50, p99]


if __name__ == "__main__":
    main()
