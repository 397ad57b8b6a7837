"""``torchseam robot``: forward/inverse kinematics and the reachability gate on the command line.

Sub-commands (joints are controller values in degrees, poses are x y z in mm in the robot base
plus an ABB quaternion q1..q4 = w, x, y, z)::

    torchseam robot fk --joints 0,0,0,0,30,0        # -> x y z q1 q2 q3 q4 of tool0
    torchseam robot ik 900 0 800 0 0 1 0 --tool torch
                                                    # -> A1 .. A6, or "unreachable: <reason>"
    torchseam robot check poses.csv                 # one verdict per pose + a summary
    torchseam robot rapid --out TorchseamWeld.mod   # the shipped RAPID module (stdout without)

``check`` reads a pose CSV (:mod:`torchseam.core.poses_csv`: header ``x,y,z,q1,q2,q3,q4`` in
any order, the torch TCP pose in the base frame, mm, quaternion w, x, y, z; optionally ``t``,
the time stamp of the pose, s). Without ``t`` the time between poses is the TCP distance at the
cell's weld speed. ``torchseam plan --out``, ``torchseam demo`` and
:func:`torchseam.live.ring.write_ring_poses` write such files.

``rapid`` prints (or writes) the RAPID module that runs a weld with the sensor guiding over EGM
(``torchseam/rapid/TorchseamWeld.mod``, shipped with the package; its data channel's layout is
:mod:`torchseam.robot.egm.rapid_data`).

Exit codes: 0 all poses fine, 1 a pose is unreachable / refused, 2 bad input.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from torchseam.core.cliargs import out_file_arg
from torchseam.core.errors import TorchseamError
from torchseam.core.poses_csv import NORM_TOLERANCE, POSE_COLUMNS, read_pose_csv

#: the shipped RAPID module (in the package's ``rapid`` folder: the repository's ``rapid/``)
RAPID_MODULE = "TorchseamWeld.mod"


def register(subparsers: Any) -> None:
    """Add the ``robot`` command group (fk, ik, check, rapid, and the EGM commands)."""
    p = subparsers.add_parser(
        "robot", help="IRB 1410 kinematics, reachability checks and the EGM link",
        description="ABB IRB 1410 model: forward/inverse kinematics and the reachability gate. "
                    "Joints in controller degrees; poses in the base frame, mm, quaternion "
                    "w x y z (ABB order).")
    sub = p.add_subparsers(dest="robot_command", metavar="ROBOT_COMMAND", required=True)

    fk = sub.add_parser("fk", help="tool0 pose of controller joints",
                        description="Print x y z q1 q2 q3 q4 of tool0 (flange) in the base frame.")
    fk.add_argument("--joints", required=True, metavar="A1,...,A6",
                    help="six controller joint values in degrees, comma separated")
    _common(fk)
    fk.set_defaults(func=run_fk)

    ik = sub.add_parser("ik", help="controller joints reaching a pose",
                        description="Print the controller joints (deg) reaching the pose, or "
                                    "'unreachable: <reason>' (exit code 1). Checks reach, axis "
                                    "ranges and the singularity margin. The pose is of the "
                                    "flange (tool0, as `robot fk` prints it) unless --tool "
                                    "torch says it is the torch tip (the TCP of the cell "
                                    "config's tool), as `robot check` and the weld take it.")
    for name in POSE_COLUMNS:
        unit = ("mm, robot base frame" if name in ("x", "y", "z")
                else "unit quaternion, w x y z order")
        ik.add_argument(name.upper(), type=float, help=f"pose {name} ({unit})")
    ik.add_argument("--tool", choices=("tool0", "torch"), default="tool0",
                    help="the pose is of tool0, the flange (default), or of the torch tip "
                         "(the TCP of the cell config's tool)")
    ik.add_argument("--seed", metavar="A1,...,A6", default=None,
                    help="joints to stay close to (default: home_deg of the robot config)")
    _common(ik)
    ik.set_defaults(func=run_ik)

    ck = sub.add_parser("check", help="check a CSV list of torch poses",
                        description="Check torch-tip poses from a CSV file (header "
                                    "x,y,z,q1,q2,q3,q4 and optional t in s) with the "
                                    "reachability gate; one verdict per pose, then a summary. "
                                    "Exit code 1 if any pose is refused. The poses are of the "
                                    "torch tip (the TCP of --cell's tool, as the weld "
                                    "commands it and `demo`/`plan` write poses*.csv), not of "
                                    "the flange: for a flange pose use `robot ik` (its "
                                    "default --tool tool0).")
    ck.add_argument("path", type=Path,
                    help="CSV file of torch-tip poses in the robot base frame (mm, "
                         "quaternion w x y z), in path order")
    ck.add_argument("--part", default=None, metavar="YAML|none",
                    help="part for the clearance check (default configs/parts/t_joint.yaml; "
                         "'none' skips it)")
    ck.add_argument("--seed", metavar="A1,...,A6", default=None,
                    help="joints the path starts from (default: home_deg of the robot "
                         "config)")
    _common(ck)
    ck.set_defaults(func=run_check)

    rp = sub.add_parser("rapid", help="print the RAPID module that runs a weld over EGM",
                        description="Print the RAPID module (TorchseamWeld.mod) that runs a weld "
                                    "segment by segment with the sensor guiding over EGM and "
                                    "the arc switched through the EGM RAPID data channel. Its "
                                    "header says what the integrator fills in and what was "
                                    "not verified (it has not run on a controller).")
    rp.add_argument("--out", type=out_file_arg, default=None, metavar="FILE",
                    help="write the module to FILE instead of printing it (default: print "
                         "to stdout)")
    rp.set_defaults(func=run_rapid)

    # the EGM helper's commands (sim-controller) live in their own module
    from torchseam.robot import egm_cli

    egm_cli.register(sub)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot-config", default=None, metavar="YAML",
                   help="robot limits and gate settings (default configs/robot.yaml)")
    p.add_argument("--cell", default=None, metavar="YAML",
                   help="cell configuration with the tool (default configs/cell.yaml)")
    p.add_argument("--urdf", default=None, metavar="URDF",
                   help="robot description (default urdf/irb1410.urdf)")


def parse_joints(text: str, what: str = "--joints") -> list[float]:
    """``"0,10,-5,0,30,0"`` -> six floats; raises :class:`TorchseamError` naming ``what``."""
    parts = [x.strip() for x in text.split(",")]
    try:
        values = [float(x) for x in parts]
    except ValueError:
        raise TorchseamError(f"{what}: expected 6 comma-separated numbers (degrees), got "
                             f"{text!r}") from None
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise TorchseamError(f"{what}: expected 6 finite comma-separated numbers (degrees), "
                             f"got {text!r}")
    return values


def _robot(args: argparse.Namespace) -> Any:
    import torch

    from torchseam.robot.kinematics import load_irb1410

    torch.set_num_threads(1)  # tiny batches: one thread is fastest
    return load_irb1410(args.robot_config, args.urdf)


def _fmt(values: Any, digits: int) -> str:
    return " ".join(f"{float(v):.{digits}f}" for v in values)


def run_fk(args: argparse.Namespace) -> int:
    import torch

    from torchseam.robot.kinematics import pose_to_xyzq

    q = parse_joints(args.joints)
    robot = _robot(args)
    xyzq = pose_to_xyzq(robot.fk([q]))[0]
    print(f"{_fmt(xyzq[:3], 3)} {_fmt(xyzq[3:], 6)}")
    # FK is defined outside the axis ranges, but the robot cannot stand there: say so (stderr,
    # so that the pose line stays the only output a script reads)
    excess = robot.range_excess(torch.as_tensor([q], dtype=robot.dtype))[0].tolist()
    lo, hi = robot.min_deg.tolist(), robot.max_deg.tolist()
    what = "axis3 - axis2" if robot.axis3_difference else "axis 3"
    for i, e in enumerate(excess):
        if e != 0.0:
            name = what if i == 2 else f"axis {i + 1}"
            print(f"note: {name} is {e:+.3f} deg outside its range {lo[i]:g}..{hi[i]:g} "
                  f"(robot config): the robot cannot reach these joints", file=sys.stderr)
    return 0


def run_ik(args: argparse.Namespace) -> int:
    import numpy as np

    from torchseam.core.config import load_cell
    from torchseam.core.transforms import pose_matrix
    from torchseam.robot.reach import ReachGate

    pose = [getattr(args, n.upper()) for n in POSE_COLUMNS]
    if not all(math.isfinite(v) for v in pose):
        raise TorchseamError(f"pose: expected finite numbers, got {pose}")
    quat = np.asarray(pose[3:])
    norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > NORM_TOLERANCE:
        raise TorchseamError(f"pose: quaternion Q1..Q4 (w, x, y, z) must have norm 1, "
                             f"got {norm:.6f}")
    robot = _robot(args)
    cell = load_cell(args.cell)
    T = pose_matrix(np.asarray(pose[:3]), quat / norm)
    if args.tool == "tool0":
        T = T @ cell.tool.matrix()  # the gate takes TCP poses: tool0 pose -> TCP pose
    seed = (np.asarray(parse_joints(args.seed, "--seed"), float) if args.seed is not None
            else None)
    r = ReachGate(robot, cell=cell).check(T[None], q_start_deg=seed)  # no part, no speed
    if not bool(r.ok[0]):
        print(f"unreachable: {r.reasons[0]}")
        return 1
    print(_fmt(r.q_deg[0], 3))
    return 0


def run_check(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from torchseam.core.config import load_cell, load_part
    from torchseam.robot.reach import ReachGate

    poses = read_pose_csv(args.path)  # a bad file: PoseFileError, one line naming file/line/field
    T, t = poses.T, poses.t
    robot = _robot(args)
    cell = load_cell(args.cell)
    part = None if (args.part or "").lower() == "none" else load_part(args.part)
    gate = ReachGate(robot, cell=cell, part=part)
    seed = (np.asarray(parse_joints(args.seed, "--seed"), float) if args.seed is not None
            else None)
    dt = None if t is None else np.concatenate([[0.0], np.diff(t)])
    t0 = time.perf_counter()
    r = gate.check(T, q_start_deg=seed, dt_s=dt)
    elapsed = time.perf_counter() - t0
    width = len(str(len(r) - 1))
    for i in range(len(r)):
        if r.code[i].value == "ok":
            print(f"{i:>{width}} ok {_fmt(r.q_deg[i], 3)}")
        else:
            print(f"{i:>{width}} refused: {r.reasons[i]}")
    print(f"{r.summary()}; checked in {elapsed * 1e3:.1f} ms")
    return 0 if bool(r.ok.all()) else 1


def rapid_module_path() -> Path:
    """The shipped RAPID module (:data:`RAPID_MODULE` in the package's ``rapid`` folder)."""
    import torchseam

    return torchseam.shipped("rapid") / RAPID_MODULE


def run_rapid(args: argparse.Namespace) -> int:
    """Entry point of ``torchseam robot rapid``: the module's text, unchanged, to stdout or
    ``--out`` (a folder or an unwritable path: one line on stderr, exit code 2)."""
    text = rapid_module_path().read_text(encoding="ascii")
    if args.out is None:
        sys.stdout.write(text)
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text, encoding="ascii")
    print(f"wrote {args.out}")
    return 0
