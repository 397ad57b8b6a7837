"""The seam search from random starts off the seam (``torchseam demo --start-offset-mm
--start-angle-deg``).

    .venv/bin/python bench/search.py [--parts t_joint,y_joint_75,...] [--runs 20] [--seed 0]
                                     [--length-mm 2]

Per part (configs/parts/<name>.yaml; default every joint kind: the T joint, the Y joints of 75
and 60 degrees, the pipe on a plate, the pipe on a sphere, the offset branch) and run: segment a
of the closed-loop demo (:func:`torchseam.live.demo.run_demo`, heavy noise, ``--length-mm``
welded) started from its programmed start moved D mm across the seam (along the part's
surfaces), lifted by the search stand-off the demo chooses for that start (the lowest at which
the whole search region passes the reachability gate with the torch's tip off the part) and
turned A degrees about the torch axis, D uniform in [-30, 30] mm and A in [-15, 15] deg
(seeded). Columns: runs, starts refused (the gate refuses the start pose: nothing moves), seam
found (the search confirmed the stripe corner, triangulated it within the offset limit, and the
approach brought the torch onto it), time to find it (median / max, s of simulated time), the
approach from there onto the seam found (median / max s), the stand-offs chosen, the farthest
the search went from the start (mm / deg, max), how far the weld started from the true seam
(max mm; the programmed start's own distance in brackets), poses the reachability gate refused
to the search (its legs cut short), unsafe poses (the demo's independent re-check of every
pose sent and put on the wire, search and approach included), poses the link refused, segments
not welded to their end, wall time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchseam.core.config import CONFIG_DIR, load_cell, load_noise, load_part
from torchseam.core.errors import TorchseamError
from torchseam.core.report import format_table
from torchseam.live.demo import run_demo
from torchseam.live.parts import load_live_parts
from torchseam.plan.preflight import preflight

PARTS = ("t_joint", "y_joint_75", "y_joint_60", "pipe_on_plate", "pipe_on_sphere",
         "offset_branch")
MAX_OFFSET_MM = 30.0
MAX_ANGLE_DEG = 15.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--length-mm", type=float, default=2.0)
    args = ap.parse_args()
    for name in args.parts.split(","):
        if not (CONFIG_DIR / "parts" / f"{name}.yaml").is_file():
            ap.error(f"--parts: {name}: no configs/parts/{name}.yaml")
    torch.set_num_threads(1)
    cell, noise, parts = load_cell(), load_noise(), load_live_parts()
    rows = []
    for name in args.parts.split(","):
        part = load_part(CONFIG_DIR / "parts" / f"{name}.yaml")
        report = preflight(cell, part, config=parts.plan, robot=parts.robot, part_name=name)
        rng = np.random.default_rng(args.seed)
        found, t_find, t_app, ext_mm, ext_deg = 0, [], [], [], []
        lifts, start_err, prog_err = set(), [], []
        gate_ref = unsafe = refused = incomplete = start_refused = 0
        t0 = time.perf_counter()
        for i in range(args.runs):
            d = float(rng.uniform(-MAX_OFFSET_MM, MAX_OFFSET_MM))
            a = float(rng.uniform(-MAX_ANGLE_DEG, MAX_ANGLE_DEG))
            try:
                res = run_demo(cell, part, noise, noise.level("heavy"), args.seed + i,
                               segments="a", length_mm=args.length_mm, report=report,
                               start_offset_mm=d, start_angle_deg=a, parts=parts)
            except TorchseamError as e:
                start_refused += 1
                print(f"{name} run {i}: D {d:+6.1f} mm, A {a:+5.1f} deg: {e}", flush=True)
                continue
            s = res.summary
            (srch,) = s["search"]
            if srch["reason"].startswith("start pose refused"):  # nothing moved
                start_refused += 1
                print(f"{name} run {i}: D {d:+6.1f} mm, A {a:+5.1f} deg: {srch['reason']}",
                      flush=True)
                continue
            found += int(srch["found"])
            t_find.append(srch["time_s"])
            lifts.add(srch["standoff_mm"])
            if srch["found"]:
                t_app.append(srch["approach_s"])
                start_err.append(srch["start_error_mm"])
                prog_err.append(srch["programmed_start_error_mm"])
            ext_mm.append(srch["extent_mm"])
            ext_deg.append(srch["extent_deg"])
            gate_ref += srch["gate_refused"]
            unsafe += s["unsafe_poses_sent"]
            refused += s["poses_refused"]
            incomplete += len(s["segments_incomplete"])
            print(f"{name} run {i}: D {d:+6.1f} mm, A {a:+5.1f} deg: "
                  + (f"found in {srch['time_s']:.2f} s at a {srch['standoff_mm']:g} mm "
                     f"stand-off, weld started {srch['start_error_mm']:.2f} mm from the seam"
                     if srch["found"] else srch["reason"]),
                  flush=True)
        rows.append([name, args.runs, start_refused, found,
                     f"{np.median(t_find):.2f} / {np.max(t_find):.2f}" if t_find else "-",
                     f"{np.median(t_app):.2f} / {np.max(t_app):.2f}" if t_app else "-",
                     ", ".join(f"{v:g}" for v in sorted(lifts)) or "-",
                     f"{max(ext_mm):.1f} / {max(ext_deg):.1f}" if ext_mm else "-",
                     f"{max(start_err):.2f} ({max(prog_err):.1f})" if start_err else "-",
                     gate_ref,
                     unsafe, refused,
                     incomplete, f"{time.perf_counter() - t0:.0f}"])
    print(f"\nseam search, starts D in +-{MAX_OFFSET_MM:g} mm across the seam, A in "
          f"+-{MAX_ANGLE_DEG:g} deg about the torch axis, seed {args.seed}, heavy noise, "
          f"segment a ({args.length_mm:g} mm welded)")
    print(format_table(["part", "runs", "start refused", "found", "find s (med / max)",
                        "approach s (med / max)", "stand-off mm",
                        "search extent mm / deg (max)", "start off seam mm (programmed)",
                        "gate-cut legs", "unsafe poses", "link refused", "incomplete", "wall s"],
                       rows))


if __name__ == "__main__":
    main()
