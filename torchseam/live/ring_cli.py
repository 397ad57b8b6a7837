"""``torchseam ring``: the whole ring in open loop; error table and the paper's figures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from torchseam.core.cliargs import model_arg, out_dir_arg, seed_arg, segments_arg
from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.errors import TorchseamError
from torchseam.core.report import format_table
from torchseam.track.names import TRACKERS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "ring", help="locate and plan the whole ring in open loop; error table and plots",
        description="Run the sensor along the nominal path of each of the six segments, track "
                    "the seam through arc noise, locate it in 3D and plan the torch path; print "
                    "the errors against the simulator's true seam (tracked path vs the nominal "
                    "path) and write q1..q4 along each segment.")
    p.add_argument("--noise", default="heavy", help="arc-noise level (default heavy)")
    p.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    p.add_argument("--tracker", choices=TRACKERS, default="anchored",
                   help="feature-point tracker (default anchored: EAKF-STC fused with TIPM)")
    p.add_argument("--segments", type=segments_arg, default="abcdef",
                   help="which segments, each letter once (default abcdef)")
    p.add_argument("--model", type=model_arg, default=None, metavar="FILE",
                   help="tracker model file for the anchored and eakf-stc trackers, e.g. a "
                        "run's runs/NAME/live_tracker.safetensors (default "
                        "models/live_tracker.safetensors)")
    p.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml)")
    p.add_argument("--out", type=out_dir_arg, default=Path("ring_out"),
                   help="folder for quaternions.png, ring.json, commands.csv and poses.csv "
                        "(default ring_out)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # imported here: the parser (--help) needs no torch, OpenCV or matplotlib
    import cv2
    import torch
    from tqdm import tqdm

    from torchseam.live.parts import load_live_parts
    from torchseam.live.plots import quaternion_plot
    from torchseam.live.ring import ring_errors, run_ring, write_ring_poses

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    cell, part, noise = load_cell(), load_part(args.part), load_noise()
    try:
        level = noise.level(args.noise)
    except ValueError as e:
        raise TorchseamError(f"--noise: {e}") from None
    which = sorted({"abcdef".index(c) for c in args.segments})
    args.out.mkdir(parents=True, exist_ok=True)
    bar = tqdm(desc="ring", unit="frame")
    runs = run_ring(cell, part, noise, level, args.seed, args.tracker, which,
                    progress=bar.update, model_path=args.model, parts=load_live_parts())
    bar.close()
    errs = ring_errors(runs)

    def row(name: str, v: np.ndarray, unit: str) -> list:
        f = v[np.isfinite(v)]
        if not len(f):   # every one missing (nothing located, no torch frame): say so
            return [name, unit, len(v), len(v), "-", "-", "-"]
        return [name, unit, len(v), len(v) - len(f), float(np.sqrt(np.mean(f**2))),
                float(f.max()), float(np.median(f))]

    used = errs["used"]
    rows = [row("feature point", errs["pixel_px"], "px"),
            row("3D seam point (located)", errs["located_mm"], "mm"),
            row("3D seam point (used by plan)", errs["located_mm"][used], "mm"),
            row("planned path (tracked)", errs["planned_mm"], "mm"),
            row("nominal path (design)", errs["nominal_mm"], "mm"),
            row("torch axis vs bisector", errs["axis_deg"], "deg")]
    print(f"\nopen-loop ring: tracker {args.tracker}, noise {level:g}, seed {args.seed}, "
          f"segments {''.join('abcdef'[i] for i in which)}")
    print(format_table(["error of", "unit", "n", "missing", "RMSE", "max", "median"], rows))
    loc = errs["located_mm"]
    off = ~used & np.isfinite(loc)
    print(f"located points the plan did not use (flagged off the smooth seam, or no ECAL arms): "
          f"{int(off.sum())} of {int(np.isfinite(loc).sum())}; of the located points > 0.3 mm "
          f"off the true seam, {int((off & (loc > 0.3)).sum())} of {int((loc > 0.3).sum())} "
          "were not used")
    ax = errs["axis_deg"]
    print(f"torch axis within 1 degree of the bisector: {int((ax <= 1.0).sum())} of {len(ax)} "
          "commands")
    over = np.flatnonzero(~(ax <= 1.0))  # NaN (no torch frame) counts as over
    if len(over):
        print("  over 1 degree: " + ", ".join(
            f"{errs['command_segment'][i]}{errs['command_index'][i]} "
            + (f"{ax[i]:.2f}" if np.isfinite(ax[i]) else "no torch frame") for i in over[:12])
              + (f", ... ({len(over) - 12} more, see commands.csv)" if len(over) > 12 else ""))
    jumps = [float(np.abs(np.diff(r.quats, axis=0)).max()) if len(r.quats) > 1 else 0.0
             for r in runs]
    print("largest quaternion step between 2 mm points per segment: "
          + ", ".join(f"{r.segment.name} {j:.4f}" for r, j in zip(runs, jumps, strict=True)))
    quaternion_plot([(r.segment.name, r.quats) for r in runs], args.out / "quaternions.png")
    summary = {r[0]: {"unit": r[1], "n": r[2], "missing": r[3],
                      **{k: (None if v == "-" else v)
                         for k, v in zip(("rmse", "max", "median"), r[4:], strict=True)}}
               for r in rows}
    summary["located_not_used"] = {"n": int(off.sum()), "of": int(np.isfinite(loc).sum()),
                                   "over_0.3mm": int((off & (loc > 0.3)).sum()),
                                   "over_0.3mm_of": int((loc > 0.3).sum())}
    summary["axis_within_1deg"] = {"n": int((ax <= 1.0).sum()), "of": len(ax)}
    summary["quaternion_max_step"] = dict(zip([r.segment.name for r in runs], jumps,
                                              strict=True))
    (args.out / "ring.json").write_text(json.dumps(summary, indent=1))
    with open(args.out / "commands.csv", "w") as f:  # one row per planned command
        f.write("segment,command,path_error_mm,axis_error_deg\n")
        for seg, i, d, a in zip(errs["command_segment"], errs["command_index"],
                                errs["planned_mm"], ax, strict=True):
            f.write(f"{seg},{i},{d:.4f},{a:.3f}\n")
    write_ring_poses(runs, args.out / "poses.csv")  # for `torchseam robot check`
    print(f"wrote {args.out / 'quaternions.png'}, {args.out / 'ring.json'}, "
          f"{args.out / 'commands.csv'} and {args.out / 'poses.csv'}")
    return 0
