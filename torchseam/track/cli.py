"""``torchseam track`` and ``torchseam eval``: follow the feature point through a frame folder."""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchseam.core.dataset import Dataset
from torchseam.core.errors import TorchseamError
from torchseam.core.orient import STRIPE_AXES, STRIPE_RESPONSES
from torchseam.core.report import error_stats, format_table, percentiles_ms
from torchseam.track.peers import STATUS_NAMES, TRACKERS, make_tracker, run_tracker

MISSING = "missing"  # track.csv status of a frame number the folder has no image for


def _parse_init(text: str | None) -> np.ndarray | None:
    if text is None:
        return None
    try:
        u, v = (float(x) for x in text.split(","))
    except ValueError:
        raise TorchseamError(f"--init {text!r}: expected U,V (two numbers)") from None
    if not (np.isfinite(u) and np.isfinite(v)):
        raise TorchseamError(f"--init {text!r}: U and V must be finite")
    return np.array([u, v])


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("frames_dir", type=Path, metavar="FRAMES_DIR",
                   help="folder of NNNNN.png frames (the dataset format)")
    p.add_argument("--tracker", choices=TRACKERS, default="anchored",
                   help="tracker (default anchored: EAKF-STC fused with TIPM, as the live loop "
                        "and demo run it; eakf-stc alone drifts along the stripe)")
    p.add_argument("--init", metavar="U,V",
                   help="start point on the first frame (default: TIPM on the first frame)")
    p.add_argument("--stripe-axis", choices=STRIPE_AXES, default="auto",
                   help="how the stripe runs in the frames: rows, columns (sensor mounted at "
                        "90 degrees) or auto: found on the first frame (default)")
    p.add_argument("--stripe-response", choices=STRIPE_RESPONSES, default="auto",
                   help="a colour stream's stripe response: red (red excess), intensity (the "
                        "red channel: a stripe overexposed into white) or auto: chosen on the "
                        "first frame (default)")
    p.add_argument("--threads", type=int, default=1,
                   help="torch and OpenCV threads (default 1: the live loop's setting)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track", help="track the feature point through a folder of frames",
        description="Track the weld feature point through FRAMES_DIR (frames in file-name "
                    "order; labels are not needed) and write frame,u,v,status per frame "
                    "number (status tracked, coasting, lost, or missing for a number the "
                    "folder has no image for).")
    _common(p)
    p.add_argument("--out", type=Path, default=Path("track.csv"),
                   help="output CSV (default track.csv)")
    p.set_defaults(func=run_track)
    e = sub.add_parser(
        "eval", help="track a labelled folder and print the error table",
        description="Track FRAMES_DIR and compare with its labels.csv: RMSE, max error, "
                    "%% frames > 5 px, %% lost (> 15 px or no point), ms per frame (frame -> "
                    "point; the tracker's learning between frames, as the live loop runs it, "
                    "is not counted).")
    _common(e)
    e.set_defaults(func=run_eval)


def _track(args: argparse.Namespace, ds: Dataset, uv0: np.ndarray | None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    tracker = make_tracker(args.tracker)
    bar = tqdm(total=len(ds), desc=f"{args.tracker} {ds.root.name}", unit="frame", leave=False)
    frames = (ds.read(i) for i in range(len(ds)))
    uv, status, secs, _, note = run_tracker(tracker, frames, uv0,
                                            progress=lambda k: bar.update(1),
                                            axis=args.stripe_axis,
                                            response=args.stripe_response)
    bar.close()
    return uv, status, secs, note


def _warn_missing(ds: Dataset) -> np.ndarray:
    """Say which frame numbers the folder lacks (the trackers take the frames on both sides
    of a gap as consecutive, so their motion model is off there); returns them."""
    gone = ds.missing
    if len(gone):
        shown = ", ".join(str(int(f)) for f in gone[:10]) + (" ..." if len(gone) > 10 else "")
        print(f"warning: {ds.root}: {len(gone)} frame number(s) missing ({shown}); the tracker "
              "takes the frames around a gap as consecutive", file=sys.stderr)
    return gone


def run_track(args: argparse.Namespace) -> int:
    uv0 = _parse_init(args.init)
    ds = Dataset.open(args.frames_dir)
    gone = _warn_missing(ds)
    uv, status, _, note = _track(args, ds, uv0)
    rows = [[int(f), f"{u:.3f}" if np.isfinite(u) and np.isfinite(v) else "",
             f"{v:.3f}" if np.isfinite(u) and np.isfinite(v) else "", STATUS_NAMES[int(s)]]
            for f, (u, v), s in zip(ds.frames, uv, status, strict=True)]
    rows += [[int(f), "", "", MISSING] for f in gone]  # one row per frame number, none dropped
    rows.sort(key=lambda r: r[0])
    with args.out.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "u", "v", "status"])
        w.writerows(rows)
    counts = {STATUS_NAMES[k]: int(np.sum(status == k)) for k in STATUS_NAMES}
    if len(gone):
        counts[MISSING] = len(gone)
    print(f"{args.tracker}: {len(ds)} frames -> {args.out} (start: {note}; "
          + ", ".join(f"{k} {n}" for k, n in counts.items()) + ")")
    return 0


def run_eval(args: argparse.Namespace) -> int:
    uv0 = _parse_init(args.init)
    ds = Dataset.open(args.frames_dir, require_labels=True)
    _warn_missing(ds)
    uv, status, secs, note = _track(args, ds, uv0)
    labelled = ds.labelled
    err = np.linalg.norm(uv - ds.labels, axis=1)[labelled]
    s = error_stats(err)
    p50, p99 = percentiles_ms(secs[1:] if len(secs) > 1 else secs)
    print(f"{args.tracker} on {ds.root} ({int(labelled.sum())} of {len(ds)} frames labelled; "
          f"start: {note})")
    print(format_table(["tracker", "frames", "RMSE px", "max px", "> 5 px %", "lost %",
                        "ms p50", "ms p99"],
                       [[args.tracker, s["n"], s["rmse"], s["max"], s["pct_gt5"], s["pct_lost"],
                         p50, p99]]))
    return 0
