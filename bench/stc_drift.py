"""Where plain EAKF-STC's error comes from: its signed error per block of frames, clean vs heavy.

Usage: python bench/stc_drift.py [--sequences 6] [--frames 300] [--first-seed 1000]
                                 [--levels clean,heavy] [--sigmas fitted,16] [--block 50]

Each sequence is simulated, started on frame 0 by TIPM (as ``bench/tracking.py``) and tracked
by the fitted EAKF-STC (``models/``, the numpy twin the live loop runs). For every sequence the
table gives the mean signed error (du / dv, px) over each block of frames, then the RMSE and
max over the arc frames (clean: every frame after the first). A noise-driven error scatters
around 0 from block to block; a drift grows block by block the same way under clean and heavy
frames. ``--sigmas`` also runs the tracker with other focus widths sigma (eq. 5, px; "fitted"
is the model's): a narrower focus weighs the arms far from the corner less.
"""

from __future__ import annotations

import argparse
import math

import cv2
import numpy as np
import torch

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.report import error_stats, format_table
from torchseam.sim.sequence import SequenceSpec, simulate_labelled
from torchseam.track.anchored import fitted_eakf_stc
from torchseam.track.fusion import LiteTracker
from torchseam.track.peers import run_tracker
from torchseam.vision.tipm import load_tipm


def tracker(sigma: str) -> LiteTracker:
    module = fitted_eakf_stc()
    if sigma != "fitted":
        with torch.no_grad():
            module.stc.log_sigma.fill_(math.log(float(sigma)))
    return LiteTracker(module)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=6)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--levels", default="clean,heavy")
    ap.add_argument("--sigmas", default="fitted,16")
    ap.add_argument("--block", type=int, default=50)
    args = ap.parse_args()
    if args.sequences < 1 or args.frames < 2 * args.block or args.block < 1:
        ap.error("need --sequences >= 1, --block >= 1 and --frames >= 2 blocks")
    sigmas = args.sigmas.split(",")
    for s in sigmas:
        if s != "fitted" and not (s.replace(".", "", 1).isdigit() and float(s) > 0):
            ap.error(f"--sigmas: {s!r} is neither 'fitted' nor a width > 0 in px")
    cell, part, noise, tipm = load_cell(), load_part(), load_noise(), load_tipm()
    for name in args.levels.split(","):
        try:
            noise.level(name)
        except ValueError as e:
            ap.error(f"--levels: {e}")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    blocks = range(0, args.frames, args.block)
    rows, totals = [], []
    for name in args.levels.split(","):
        level = noise.level(name)
        pooled: dict[str, list[np.ndarray]] = {s: [] for s in sigmas}
        for k in range(args.sequences):
            seed = args.first_seed + k
            spec = SequenceSpec(n_frames=args.frames, level=level, seed=seed)
            frames, labels, arc = simulate_labelled(cell, part, noise, spec)
            if not arc.any():
                arc[1:] = True
            for s in sigmas:
                uv = run_tracker(tracker(s), frames, None, tipm)[0]
                err = uv - labels
                st = error_stats(np.linalg.norm(err[arc], axis=1))
                pooled[s].append(np.linalg.norm(err[arc], axis=1))
                rows.append([name, s, seed]
                            + [f"{m[0]:+.2f} / {m[1]:+.2f}"
                               for m in (err[b:b + args.block].mean(axis=0) for b in blocks)]
                            + [st["rmse"], st["max"]])
            print(f"  {name}: sequence {k + 1}/{args.sequences} done", flush=True)
        for s in sigmas:
            st = error_stats(np.concatenate(pooled[s]))
            totals.append([name, s, st["n"], st["rmse"], st["max"], st["pct_lost"]])
    heads = [f"{b}-{min(b + args.block, args.frames) - 1} du / dv" for b in blocks]
    print(f"\nPlain EAKF-STC (fitted model, numpy twin), mean signed error per {args.block} "
          f"frames (px), {args.sequences} sequences x {args.frames} frames")
    print(format_table(["noise", "sigma", "seed", *heads, "RMSE px", "max px"], rows))
    print()
    print(format_table(["noise", "sigma", "frames", "RMSE px", "max px", "lost %"], totals))


if __name__ == "__main__":
    main()
