"""Are the anchored tracker's TIPM fix covariances right? Errors and Mahalanobis^2 by glare.

Usage: python bench/fix_calibration.py [--sequences 16] [--seeds 1000-1005,1020-1029]
                                       [--level heavy] [--frames 300] [DATASET ...]

The ``anchored`` tracker (``configs/anchor.yaml``) runs on each sequence, started on the
labelled first frame; every frame where TIPM found a corner gives one row: the corner's error
against the label, its Mahalanobis^2 under the covariance the tracker gave it, without and with
the glare term (``glare_start``, ``glare_scale``), and the red glare around the predicted point
(``AnchoredTracker.glare``). For a right covariance Mahalanobis^2 follows chi^2 with 2 degrees
of freedom: mean 2, median 1.39, in every glare bin. A mean well above 2 in some bin says the
tracker trusts those fixes too much; refit ``glare_start`` / ``glare_scale`` until the "with
glare term" column is flat. Give dataset folders (frames + labels.csv, e.g. a real recording)
to measure on them instead of simulated sequences.
"""

from __future__ import annotations

import argparse
import sys

import cv2
import numpy as np
import torch

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.dataset import Dataset
from torchseam.core.errors import TorchseamError
from torchseam.core.report import format_table
from torchseam.sim.sequence import SequenceSpec, simulate_labelled
from torchseam.track.anchored import AnchoredTracker, load_anchored_model
from torchseam.vision.tipm import load_tipm

BINS = (0, 20, 40, 60, 80, 100, 256)  # glare, grey levels


def parse_seeds(text: str) -> list[int]:
    """'1000-1005,1020' -> [1000, ..., 1005, 1020]."""
    seeds: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        try:
            seeds += list(range(int(lo), int(hi or lo) + 1))
        except ValueError:
            raise TorchseamError(
                f"--seeds: {part!r} is not a seed or a range like 1000-1005") from None
    return seeds


def fix_rows(frames, labels: np.ndarray) -> list[tuple[float, float, float, float, bool]]:
    """(glare, error px, Mahalanobis^2 without / with the glare term, taken) per TIPM corner."""
    trk = AnchoredTracker(load_anchored_model(), load_tipm())
    rows = []
    it = iter(frames)
    trk.init(next(it), labels[0])
    for k, frame in enumerate(it, start=1):
        trk.update(frame)
        f = trk.fix
        if f is None or not np.all(np.isfinite(labels[k])):
            continue
        e = f.uv - labels[k]
        m2 = float(e @ np.linalg.solve(f.cov, e))
        rows.append((trk.glare, float(np.linalg.norm(e)), m2, m2 / f.inflate, f.taken))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="*", help="dataset folders with labels.csv (default: "
                    "simulated sequences)")
    ap.add_argument("--seeds", default="1000-1005,1020-1029")
    ap.add_argument("--level", default="heavy", help="arc-noise level of simulated sequences")
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    if args.frames < 2:
        ap.error("--frames: need at least 2 (the tracker starts on the first)")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    rows = []
    try:
        if args.datasets:
            for root in args.datasets:
                ds = Dataset.open(root, require_labels=True)
                if not ds.labelled[0]:
                    raise TorchseamError(f"{root}: the first frame has no label (the tracker "
                                         "starts there)")
                rows += fix_rows(iter(ds), ds.labels)
                print(f"  {root}: done", flush=True)
        else:
            cell, part, noise = load_cell(), load_part(), load_noise()
            level = noise.level(args.level)
            seeds = parse_seeds(args.seeds)
            for i, seed in enumerate(seeds):
                spec = SequenceSpec(n_frames=args.frames, level=level, seed=seed)
                frames, labels, _ = simulate_labelled(cell, part, noise, spec)
                rows += fix_rows(frames, labels)
                print(f"  sequence {i + 1}/{len(seeds)} (seed {seed}) done", flush=True)
    except TorchseamError as e:
        sys.exit(f"error: {e}")
    if not rows:
        sys.exit("error: TIPM found no corner on any frame: nothing to calibrate")
    r = np.array(rows, float)
    table = []
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        m = (r[:, 0] >= lo) & (r[:, 0] < hi)
        if not m.any():
            continue
        table.append([f"{lo}-{hi}", int(m.sum()), 100.0 * r[m, 4].mean(),
                      float(np.sqrt(np.mean(r[m, 1] ** 2))), float(np.percentile(r[m, 1], 95)),
                      float(r[m, 2].mean()), float(np.median(r[m, 2])),
                      float(r[m, 3].mean()), float(np.median(r[m, 3]))])
    print(f"\nTIPM fixes of the anchored tracker ({len(r)} corners); Mahalanobis^2 of a right "
          "covariance: mean 2, median 1.39")
    print(format_table(["glare", "fixes", "taken %", "err RMS px", "err p95 px",
                        "M2 mean", "M2 median", "M2 mean (glare term)",
                        "M2 median (glare term)"], table))


if __name__ == "__main__":
    main()
