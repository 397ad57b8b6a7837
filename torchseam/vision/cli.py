"""``torchseam detect``: TIPM feature point of single frames."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from torchseam.core.config import load_cell
from torchseam.core.dataset import read_frame
from torchseam.core.errors import FrameError
from torchseam.vision.tipm import Tipm, draw_overlay


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "detect", help="find the weld feature point in frames (TIPM, clean frames)",
        description="Run TIPM on each frame and print 'FILE u v' or 'FILE none: <reason>'.")
    p.add_argument("frames", nargs="+", type=Path, metavar="FRAME", help="BGR image files")
    p.add_argument("--overlay", type=Path, metavar="DIR",
                   help="write an overlay image per frame into DIR")
    p.add_argument("--cell", type=Path,
                   help="cell config giving the camera size (default configs/cell.yaml)")
    p.add_argument("--centre-line", choices=("subpixel", "thinning"), default="subpixel",
                   help="centre-line method (default subpixel; thinning as in the paper)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cam = load_cell(args.cell).camera
    size = (cam.width, cam.height)
    tipm = Tipm(centre_line=args.centre_line)
    if args.overlay:
        args.overlay.mkdir(parents=True, exist_ok=True)
    found = 0
    for path in args.frames:
        try:
            img = read_frame(path, size)
        except FrameError as e:
            print(f"{path} error: {e}")
            continue
        res = tipm(img)
        found += res.ok
        print(f"{path} {res.uv[0]:.3f} {res.uv[1]:.3f}" if res.ok else f"{path} none: {res.reason}")
        if args.overlay:
            cv2.imwrite(str(args.overlay / f"{path.stem}_tipm.png"), draw_overlay(img, res))
    # exit 1 when no frame gave a point, so scripts notice
    return 0 if found else 1
