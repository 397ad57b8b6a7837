"""Time one training epoch of EAKF-STC (issue: fit the tracker) on synthetic crops.

Usage::

    python bench/fit.py [--sequences 64] [--frames 300] [--roi 256] [--batch 16] [--chunk 16]
    torchrun --nproc_per_node 2 bench/fit.py ...      # DDP, gloo, one shard per process

The crops are a V-shaped stripe moved along a random walk, with read noise (uint8, the size
of real ROI crops): the tracker's cost per frame does not depend on the image content (fixed
FFT sizes), so this times what an epoch on 64 real sequences x 300 frames costs, without
simulating 19 200 frames first. Prints seconds per epoch and frames per second.
"""

from __future__ import annotations

import argparse
import platform

import numpy as np
import torch
import torch.distributed as dist

from torchseam.fit.config import FitConfig
from torchseam.fit.data import SequenceSet
from torchseam.fit.synthetic import render_v_stripes
from torchseam.fit.train import init_distributed, train


def synthetic_set(n: int, T: int, roi: int, seed: int = 0) -> SequenceSet:
    rng = np.random.default_rng(seed)
    base = render_v_stripes(np.array([[roi / 2, roi / 2]]), (roi, roi), noise=0.0)[0]
    frames, labels = [], []
    for _ in range(n):
        walk = np.cumsum(rng.normal(0, 0.7, (T, 2)), axis=0)
        walk = np.clip(np.round(walk), -roi / 4, roi / 4).astype(int)
        seq = np.empty((T, roi, roi), np.uint8)
        for k, (du, dv) in enumerate(walk):
            img = np.roll(base, (dv, du), axis=(0, 1)).astype(np.int16)
            img += rng.integers(-6, 7, img.shape, dtype=np.int16)
            seq[k] = np.clip(img, 0, 255)
        frames.append(seq)
        labels.append((roi / 2 + walk).astype(np.float32))
    return SequenceSet(frames, labels, np.zeros((n, 2), int), ["synthetic"] * n,
                       ["synthetic"] * n, roi)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=64)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--roi", type=int, default=256)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--chunk", type=int, default=16)
    ap.add_argument("--threads", type=int, default=1, help="torch threads per process")
    ap.add_argument("--epochs", type=int, default=1)
    args = ap.parse_args()
    info = init_distributed()
    torch.set_num_threads(args.threads)
    data = synthetic_set(args.sequences, args.frames, args.roi)
    cfg = FitConfig(epochs=args.epochs, batch=args.batch, chunk=args.chunk, progress=False,
                    out="runs/bench-fit", threads=args.threads)
    _, hist = train(cfg, data, None, info=info, log_fn=lambda s: None)
    if info.main:
        frames = args.sequences * (args.frames - 1)
        gb = args.sequences * args.frames * args.roi**2 / 1e9
        print(f"{args.sequences} sequences x {args.frames} frames, ROI {args.roi} px "
              f"({gb:.2f} GB uint8 per process), batch {args.batch}, chunk {args.chunk}; "
              f"{info.world} process(es) x {args.threads} thread(s); "
              f"{platform.processor() or platform.machine()}")
        for h in hist:
            print(f"epoch {h.epoch}: {h.seconds:.1f} s ({frames / h.seconds:.0f} frames/s, "
                  f"{h.steps} optimiser steps)")
    if info.active:
        dist.destroy_process_group()


if __name__ == "__main__":
    main()
