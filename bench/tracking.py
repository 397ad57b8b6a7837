"""Trackers compared on simulated sequences at three arc-noise levels (issue: trackers).

Usage: python bench/tracking.py [--sequences 6] [--frames 300] [--levels clean,strike,heavy]
                                [--first-seed 1000]

For every level, the same ``--sequences`` sequences (seeds ``--first-seed`` on; settings
were chosen on 1000-1019, so 1020 on are held out) go through TIPM per frame,
plain STC, KCF, CSRT, MOSSE, EAKF-STC and ``anchored`` (EAKF-STC fused with TIPM, the live
loop's default), each started on frame 0 (arc off) by TIPM. Errors are
over the arc frames against the simulator's labels: RMSE and max (px), % frames lost (no point
or > 15 px off), and the single-stream time per frame (BGR frame in memory -> point) p50/p99 on
one thread, with the tracker's work between frames (``idle()``: EAKF-STC's learning for the
next frame, which the live loop runs once the frame's command is out) timed apart. EAKF-STC
single stream is the numpy twin of the fitted module,
:class:`~torchseam.track.lite.LiteEAKFSTC`, as in the live loop. A second table times the torch
module itself: one sequence (B = 1) and B sequences stepped together.

Threads: torch.set_num_threads(1) and cv2.setNumThreads(1) for the single-stream figures (the
live loop's setting: one core per camera); the batched run uses --batch-threads (default 2).
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
from torchseam.sim.sequence import SequenceSpec, simulate_labelled
from torchseam.track.peers import TRACKERS, fitted_eakf_stc, make_tracker, run_tracker
from torchseam.vision.tipm import red_response

ORDER = ["tipm", "stc", "kcf", "csrt", "mosse", "eakf-stc", "anchored"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=6)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--levels", default="clean,strike,heavy")
    ap.add_argument("--trackers", default=",".join(ORDER))
    ap.add_argument("--first-seed", type=int, default=1000,
                    help="seed of the first sequence (1020 on: not used to choose settings)")
    ap.add_argument("--batch", type=int, default=64,
                    help="B of the batched torch run (0: skip it; default 64)")
    ap.add_argument("--batch-threads", type=int, default=2)
    args = ap.parse_args()
    if args.batch < 0 or args.batch_threads < 1:
        ap.error("--batch must be >= 0 and --batch-threads >= 1")
    trackers = args.trackers.split(",")
    for t in trackers:
        if t not in TRACKERS:
            ap.error(f"unknown tracker {t}")
    cell, part, noise = load_cell(), load_part(), load_noise()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    rows, worst = [], []
    # red responses and start points of the last level's sequences, for the batch run
    grey_bank: list[tuple[np.ndarray, np.ndarray]] = []
    for name in args.levels.split(","):
        level = noise.level(name)
        err = {t: [] for t in trackers}
        secs = {t: [] for t in trackers}
        idle = {t: [] for t in trackers}
        for s in range(args.sequences):
            spec = SequenceSpec(n_frames=args.frames, level=level, seed=args.first_seed + s)
            frames, labels, arc = simulate_labelled(cell, part, noise, spec)
            if name == args.levels.split(",")[-1]:
                grey_bank.append((np.stack([red_response(f) for f in frames]), labels[0]))
            for t in trackers:
                uv, _, sec, idle_sec, _ = run_tracker(make_tracker(t), frames, None)
                e = np.linalg.norm(uv - labels, axis=1)
                err[t].append(e[arc] if arc.any() else e[1:])
                secs[t].append(sec[1:])
                idle[t].append(idle_sec[1:])
            print(f"  {name}: sequence {s + 1}/{args.sequences} done", flush=True)
        for t in trackers:
            # the sequence with the largest error of a point given (lost frames: their lost %):
            # a pooled max hides whether one seed or all are off
            k = int(np.argmax([np.max(e[np.isfinite(e)], initial=-1.0) for e in err[t]]))
            sk = error_stats(err[t][k])
            worst.append([name, t, args.first_seed + k, sk["rmse"], sk["max"], sk["pct_lost"]])
            st = error_stats(np.concatenate(err[t]))
            p50, p99 = percentiles_ms(np.concatenate(secs[t]))
            i50, i99 = percentiles_ms(np.concatenate(idle[t]))
            rows.append([name, t, st["n"], st["rmse"], st["max"], st["pct_gt5"], st["pct_lost"],
                         p50, p99, i50, i99])
    cpu = platform.processor() or platform.machine()
    print(f"\nTrackers on {args.sequences} sequences (seeds {args.first_seed}-"
          f"{args.first_seed + args.sequences - 1}) x {args.frames} frames per level "
          f"({cell.camera.width} x {cell.camera.height}); {cpu}, 1 thread")
    print(format_table(["noise", "tracker", "frames", "RMSE px", "max px", ">5px %", "lost %",
                        "ms p50", "ms p99", "idle p50", "idle p99"], rows))
    print("Errors over the arc frames; 'lost' = no point or > 15 px off. Time (ms): BGR frame "
          "in memory -> point, per frame, single stream; idle: the tracker's work after the "
          "point, before the next frame (its learning; the live loop runs it once the "
          "command is out).")
    print("\nWorst sequence per level and tracker (the largest error of a point given):")
    print(format_table(["noise", "tracker", "seed", "RMSE px", "max px", "lost %"], worst))
    if "eakf-stc" in trackers and grey_bank and args.batch > 0:
        batch_table(grey_bank, args.batch, args.batch_threads)


@torch.inference_mode()
def batch_table(bank: list[tuple[np.ndarray, np.ndarray]], B: int, threads: int) -> None:
    """Time the torch EAKF-STC module stepping B sequences at once (frames already grey in
    memory), and stepping one (B = 1, one thread: what the numpy twin replaces in the
    single-stream rows above)."""
    rows = []
    for b, th in ((1, 1), (B, threads)):
        torch.set_num_threads(th)
        T = min(len(g) for g, _ in bank)
        src = [bank[i % len(bank)][0] for i in range(b)]
        trk = fitted_eakf_stc()
        uv0 = torch.tensor(np.stack([bank[i % len(bank)][1] for i in range(b)]),
                           dtype=torch.float32)
        trk.init(torch.from_numpy(np.stack([g[0] for g in src])).float(), uv0)
        step_s = []
        for k in range(1, T):
            fr = torch.from_numpy(np.stack([g[k] for g in src])).float()
            t0 = time.perf_counter()
            trk.step(fr)
            step_s.append(time.perf_counter() - t0)
        per = np.array(step_s)
        rows.append([b, th, 1e3 * float(np.median(per)), 1e3 * float(np.percentile(per, 99)),
                     float(b / np.median(per))])
    print(f"\nEAKF-STC torch module (float32), {T - 1} steps per sequence")
    print(format_table(["B", "threads", "ms per step p50", "ms per step p99", "frames/s (p50)"],
                       rows))


if __name__ == "__main__":
    main()
