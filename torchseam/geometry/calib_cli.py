"""``torchseam calibrate``: camera, laser plane, hand-eye and TCP from a folder of views.

Folder layouts (``torchseam calibrate simulate KIND DIR`` writes one of each to try):

camera   ``DIR/*.png`` (or .jpg, .bmp, .tif): the checkerboard at 20-30 poses, tilted
         20-50 degrees about different axes, over the whole image.
laser    ``DIR/NAME_board.png`` (checkerboard, lamp on, laser off) and ``DIR/NAME_laser.png``
         (same pose, laser on, lamp dimmed) for each of 6-10 board poses across the stripe's
         depth range.
handeye  ``DIR/poses.csv`` with header ``image,x,y,z,q1,q2,q3,q4``: per image the flange
         pose in the robot base (ABB tool0 robtarget: mm, quaternion q1..q4 = w x y z) and
         the image of the board, fixed in the cell, taken there.
tcp      ``DIR/poses.csv`` with header ``pose,x,y,z,q1,q2,q3,q4``: flange poses with the
         torch tip on one fixed point, the torch tilted about different axes.

poses.csv is the pose CSV that ``robot check`` reads too: columns in any order, blank lines
and ``#`` lines skipped; the older header spelling ``x_mm,y_mm,z_mm,qw,qx,qy,qz`` is still read.

A simulated set also holds ``truth.json``; the command then prints the true values beside the
recovered ones. The result goes into a copy of ``--cell`` (default ``configs/cell.yaml``)
written to ``--write`` (default ``DIR/cell.yaml``): only the calibrated section changes, other
values and the file's comments stay.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
from pathlib import Path
from typing import Any

import numpy as np

from torchseam.core.cliargs import out_dir_arg, out_file_arg
from torchseam.core.config import config_path, load_cell
from torchseam.core.errors import TorchseamError
from torchseam.geometry.names import HAND_EYE_METHODS

KINDS = {
    "camera": ("camera", "intrinsics and distortion from checkerboard images"),
    "laser": ("laser_plane", "laser plane in the camera frame from stripe images on the board"),
    "handeye": ("hand_eye", "camera pose in the flange from robot poses and board images"),
    "tcp": ("tool", "torch TCP in the flange by pivoting about one fixed point"),
}


def register(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """Add ``calibrate`` and its kinds; returns the kinds' sub-parsers (the live stage adds
    ``latency``, which needs the cell's camera and controller, there)."""
    p = sub.add_parser(
        "calibrate", help="calibrate camera, laser plane, hand-eye or TCP from a folder",
        description=__doc__.split("\n", 2)[2].replace("``", ""),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    for kind, (section, text) in KINDS.items():
        q = kinds.add_parser(kind, help=text, description=f"{text}; writes the cell config's "
                             f"'{section}' section and prints the residuals.")
        q.add_argument("dir", type=Path, metavar="DIR", help="folder of the calibration set")
        q.add_argument("--cell", type=Path,
                       help="cell config to start from: a calibration file (default "
                            "configs/cell.yaml) or a cell file for `weld --cell` (its "
                            "calibration: section is updated, the rest kept)")
        q.add_argument("--write", type=out_file_arg, metavar="OUT.yaml",
                       help="where to write the updated cell config (default DIR/cell.yaml; "
                            "may be the --cell file itself)")
        q.add_argument("--calib", type=Path, help="calibration settings "
                       "(default configs/calibration.yaml)")
        if kind == "camera":
            q.add_argument("--skip-failed", action="store_true",
                           help="leave out images where the board is not found (default: error)")
        if kind == "handeye":
            q.add_argument("--method", choices=HAND_EYE_METHODS, default="park",
                           help="closed-form AX = XB solver of cv2.calibrateHandEye (default "
                                "park; where the installed OpenCV lacks it, as 5.0.0 does: "
                                "Park & Martin in numpy)")
            q.add_argument("--refine", action="store_true",
                           help="bundle-adjust on the reprojection error (only for near-exact "
                                "robot poses)")
        q.set_defaults(func=run)
    s = kinds.add_parser("simulate", help="write a simulated calibration set to try the procedure",
                         description="Render a calibration set of KIND with the simulated "
                                     "cell and write it to DIR with its truth (truth.json).")
    s.add_argument("set_kind", choices=tuple(KINDS), metavar="KIND",
                   help="camera, laser, handeye or tcp")
    s.add_argument("dir", type=out_dir_arg, metavar="DIR", help="output folder")
    s.add_argument("--seed", type=int, default=None, help="random seed (default: the config's)")
    s.add_argument("--views", type=int, default=None,
                   help="number of views or poses (default: configs/calibration.yaml)")
    s.add_argument("--cell", type=Path, help="the true cell (default configs/cell.yaml)")
    s.add_argument("--calib", type=Path,
                   help="calibration settings (default configs/calibration.yaml)")
    s.add_argument("--overwrite", action="store_true", help="replace a set already in DIR")
    s.set_defaults(func=run_simulate)
    return kinds


# --------------------------------------------------------------------------- commands

def run(args: argparse.Namespace) -> int:
    # imported here: the parser (--help) needs no OpenCV or scipy
    from torchseam.geometry.calibrate import (
        calibrate_camera,
        calibrate_hand_eye,
        calibrate_laser_plane,
        calibrate_tcp,
        load_calibrated_cell,
        load_calibration,
        load_camera_set,
        load_handeye_set,
        load_laser_set,
        load_tcp_set,
        update_cell,
    )

    cfg = load_calibration(args.calib)
    cell_path = Path(args.cell) if args.cell else config_path("cell.yaml")
    cell = load_calibrated_cell(cell_path)  # a calibration file or a cell file (weld --cell)
    folder = Path(args.dir)
    section, _ = KINDS[args.kind]
    out = Path(args.write) if args.write else folder / "cell.yaml"
    if args.write is None and out.is_dir():  # checked before the work (--write: by argparse)
        raise TorchseamError(f"{out} is a folder, not a file: give --write OUT.yaml")
    if args.kind == "camera":
        images, names = load_camera_set(folder)
        res: Any = calibrate_camera(images, names, cfg, skip_failed=args.skip_failed)
        value: Any = res.camera
        headline = f"RMS {res.rms_px:.4f} px, {len(res.names)} views"
    elif args.kind == "laser":
        lasers, lnames, boards, bnames = load_laser_set(folder)
        res = calibrate_laser_plane(lasers, lnames, cell.camera, cfg, boards, bnames,
                                    source_mm=cell.laser_plane.source_mm)
        value = res.plane
        headline = f"plane RMS {res.rms_mm:.4f} mm, {len(res.names)} views"
    elif args.kind == "handeye":
        images, names, T_B_F = load_handeye_set(folder)
        res = calibrate_hand_eye(images, names, T_B_F, cell.camera, cfg, method=args.method,
                                 refine=args.refine)
        value = res.hand_eye
        headline = (f"board-in-base spread RMS {float(np.sqrt(np.mean(res.view_pos_mm**2))):.4f}"
                    f" mm, {len(res.names)} poses")
    else:
        names, T_B_F = load_tcp_set(folder)
        res = calibrate_tcp(T_B_F, names, cfg, orientation=cell.tool.quaternion)
        value = res.tool
        headline = f"pivot RMS {res.rms_mm:.4f} mm, {len(res.names)} poses"
    print(f"torchseam calibrate {args.kind}: {folder}")
    for line in res.summary():
        print("  " + line)
    truth = folder / "truth.json"
    if truth.is_file():
        for line in compare_with_truth(args.kind, value, json.loads(truth.read_text())):
            print("  " + line)
    note = (f"calibrated: torchseam calibrate {args.kind} {folder} "
            f"({_dt.date.today().isoformat()}; {headline})")
    _, kept = update_cell(cell_path, out, section, value, note)
    how = "" if kept else "; written anew, the input's comments not kept"
    print(f"wrote {out} (section {section}; the rest from {cell_path}{how})")
    return 0


def run_simulate(args: argparse.Namespace) -> int:
    from torchseam.geometry.calibrate import load_calibration
    from torchseam.sim.board import write_set

    if args.views is not None and args.views < 1:
        raise TorchseamError(f"--views must be at least 1, got {args.views}")
    cfg = load_calibration(args.calib)
    cell = load_cell(args.cell)
    try:
        truth = write_set(args.set_kind, args.dir, cell, cfg, seed=args.seed, views=args.views,
                          overwrite=args.overwrite)
    except (FileExistsError, ValueError) as e:
        raise TorchseamError(str(e)) from None
    n = len(list(Path(args.dir).glob("*.png")))
    what = f"{n} images" if n else "robot poses (poses.csv)"
    print(f"wrote a simulated {args.set_kind} calibration set to {args.dir}: {what}, truth in "
          f"truth.json (seed {truth['seed']})")
    print(f"next: torchseam calibrate {args.set_kind} {args.dir}")
    return 0


# --------------------------------------------------------------------------- truth

def compare_with_truth(kind: str, value: Any, truth: dict[str, Any]) -> list[str]:
    """Lines comparing a recovered value with a simulated set's ``truth.json``."""
    from torchseam.core.transforms import pose_matrix

    out = ["vs simulator truth (truth.json):"]
    try:
        if kind == "camera":
            t = truth["camera"]
            for k in ("fx", "fy", "cx", "cy"):
                v = getattr(value, k)
                out.append(f"  {k:<4} {v:11.4f}  true {t[k]:11.4f}  error {v - t[k]:+.4f} px "
                           f"({100 * (v / t[k] - 1):+.3f} %)")
        elif kind == "laser":
            t = truth["laser_plane"]
            cosang = float(np.clip(np.dot(value.normal, t["normal"]), -1.0, 1.0))
            out.append(f"  normal error {np.degrees(np.arccos(cosang)):.4f} deg, distance error "
                       f"{value.distance_mm - t['distance_mm']:+.4f} mm")
        elif kind == "handeye":
            t = truth["hand_eye"]
            A = pose_matrix(np.asarray(value.position_mm), np.asarray(value.quaternion))
            B = pose_matrix(np.asarray(t["position_mm"]), np.asarray(t["quaternion"]))
            ang = np.degrees(np.arccos(np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2,
                                               -1.0, 1.0)))
            out.append(f"  position error {np.linalg.norm(A[:3, 3] - B[:3, 3]):.4f} mm, "
                       f"rotation error {ang:.4f} deg")
        else:
            t = truth["tool"]
            err = np.asarray(value.position_mm) - np.asarray(t["position_mm"])
            out.append(f"  TCP error {np.linalg.norm(err):.4f} mm ("
                       + " ".join(f"{x:+.4f}" for x in err) + ")")
    except (KeyError, TypeError, ValueError):
        return ["truth.json: not a simulated set of this kind; no comparison"]
    return out
