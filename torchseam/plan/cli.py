"""``torchseam plan``: plan a part's weld and check every pose with the reachability gate.

Prints the pre-flight table (:mod:`torchseam.plan.preflight`); with ``--out`` also writes
``plan.json`` (the plan and every segment's verdict), ``part.yaml`` (the part with the planned
placement) and per segment ``poses_<s>.csv`` (its torch poses, the approach included, in the
format of ``torchseam robot check``) with ``part_<s>.yaml`` (the part as the positioner turns
it for that segment), so that ``torchseam robot check DIR/poses_b.csv --part DIR/part_b.yaml``
re-checks segment b alone.

Exit codes: 0 the robot can weld the plan, 2 it cannot (the table names the segment and the
reason) or bad input.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from torchseam.core.cliargs import out_dir_arg


def register(sub: Any) -> None:
    p = sub.add_parser(
        "plan", help="plan a part's weld and check every pose with the reachability gate",
        description="Choose the part's placement on the positioner, where the six segments "
                    "start and the torch's angles (the configured plan when the IRB 1410 can "
                    "weld it, else a search with the reachability gate), then run every pose of "
                    "every segment through the gate and print one row per segment. Exit code 2 "
                    "when the robot cannot weld the part.")
    p.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml)")
    p.add_argument("--out", type=out_dir_arg, default=None,
                   help="folder for plan.json, part.yaml and each segment's poses_<s>.csv and "
                        "part_<s>.yaml (default: print only)")
    p.add_argument("--no-search", action="store_true",
                   help="check the configured plan only")
    p.add_argument("--robot-config", default=None, metavar="YAML",
                   help="robot limits and gate settings (default configs/robot.yaml)")
    p.add_argument("--plan-config", default=None, metavar="YAML",
                   help="planning settings and search limits (default configs/plan.yaml)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from torchseam.core.config import load_cell, load_part
    from torchseam.plan.path import load_plan_config
    from torchseam.plan.preflight import preflight
    from torchseam.robot.kinematics import load_irb1410

    torch.set_num_threads(1)  # small batches: one thread is fastest
    cell = load_cell()
    part = load_part(args.part)
    config = load_plan_config(args.plan_config)
    robot = load_irb1410(args.robot_config)
    name = str(args.part) if args.part else "configs/parts/t_joint.yaml"
    report = preflight(cell, part, config=config, robot=robot, search=not args.no_search,
                       part_name=name)
    print(report.text(verdict=False), flush=True)
    if args.out is not None:
        files = write_plan(report, args.out, cell, config, robot)
        print("wrote " + ", ".join(str(f) for f in files), flush=True)
    if not report.ok:  # the one error line, on stderr (the table above says where and why)
        print(f"torchseam plan: error: {report.refused_line()}", file=sys.stderr)
        return 2
    return 0


def write_plan(report: Any, out: Path, cell: Any, config: Any, robot: Any) -> list[Path]:
    """``plan.json``, ``part.yaml`` and per segment ``poses_<s>.csv`` / ``part_<s>.yaml`` of a
    :class:`~torchseam.plan.preflight.PlanReport` made with ``cell`` and ``config``."""
    from torchseam.core.config import Pose, save_config
    from torchseam.core.poses_csv import write_pose_csv
    from torchseam.core.transforms import matrix_to_quat
    from torchseam.plan.weld import PlanEvaluator

    out.mkdir(parents=True, exist_ok=True)
    plan = report.plan
    files = [out / "plan.json", out / "part.yaml"]
    (out / "plan.json").write_text(json.dumps(report.to_dict(), indent=1))
    save_config(plan.part, out / "part.yaml")
    # the poses the gate checked: the evaluator rebuilds them (same part, cell and plan)
    ev = PlanEvaluator(cell, report.configured_plan.part, config, robot)
    speed, dt_min = cell.process.weld_speed_mm_s, 1.0 / cell.process.frame_rate_hz
    for seg in plan.segments:
        T = ev.poses(plan.placement, seg)
        step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / speed
        t = np.concatenate([[0.0], np.cumsum(np.maximum(step, dt_min))])
        files.append(write_pose_csv(out / f"poses_{seg.name}.csv", T[:, :3, 3],
                                    matrix_to_quat(T[:, :3, :3]), t))
        P = ev.part_pose(plan.placement, seg)
        q = matrix_to_quat(P[:3, :3])
        turned = dataclasses.replace(plan.part, placement=Pose(
            tuple(float(v) for v in P[:3, 3]), tuple(float(v) for v in q / np.linalg.norm(q))))
        save_config(turned, out / f"part_{seg.name}.yaml")
        files.append(out / f"part_{seg.name}.yaml")
    return files
