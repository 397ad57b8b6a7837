"""``torchseam simulate``: write a simulated sequence in the dataset format."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from torchseam.core.cliargs import MAX_SEED, out_dir_arg, seed_arg
from torchseam.core.config import (
    FAMILY_NAMES,
    MAX_NOISE_LEVEL,
    load_cell,
    load_noise,
    load_part,
)
from torchseam.core.errors import TorchseamError
from torchseam.sim.names import CAMERAS

if TYPE_CHECKING:  # imported when the command runs: the parser (--help) needs no OpenCV
    import numpy as np

#: largest ``--start-mm`` (the seam is a closed ring of well under a metre: larger values are
#: typos, and at 1e16 mm a frame's step no longer changes the float)
MAX_START_MM = 1e6


def add_world_options(p: argparse.ArgumentParser) -> None:
    """Options naming the cell, part and noise model files (shared by several commands)."""
    p.add_argument("--cell", type=Path, help="cell config (default configs/cell.yaml)")
    p.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml)")
    p.add_argument("--noise-model", type=Path, help="noise model (default configs/noise.yaml)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate", help="render a simulated laser-sensor sequence with ground truth",
        description="Render frames of the simulated sensor riding along the seam and write them "
                    "as a dataset folder: NNNNN.png, labels.csv (frame,u,v), meta.json.")
    p.add_argument("out", type=out_dir_arg, help="output folder")
    p.add_argument("--frames", type=int, default=100, help="number of frames (default 100)")
    p.add_argument("--noise", default="clean",
                   help="arc-noise level: a name from configs/noise.yaml (clean, light, strike, "
                        f"heavy, extreme) or a number in [0, {MAX_NOISE_LEVEL:g}] (default clean)")
    p.add_argument("--family", choices=FAMILY_NAMES, default=None, metavar="NAME",
                   help="appearance family from the noise model's families: "
                        f"{', '.join(FAMILY_NAMES)} (default: its `family`)")
    p.add_argument("--seed", type=seed_arg, default=0,
                   help=f"random seed, 0 .. {MAX_SEED} (default 0)")
    p.add_argument("--start-mm", type=float, default=None,
                   help="seam arc length at the first frame (default: random from the seed)")
    p.add_argument("--preview", action="store_true",
                   help="also write preview.png: a contact sheet with the true point drawn")
    p.add_argument("--camera", choices=CAMERAS, default="colour",
                   help="the frames as a colour camera gives them (BGR, the default), or as a "
                        "mono camera behind the 650 nm band-pass does: mono (8 bit) or mono16 "
                        "(16-bit PNG)")
    p.add_argument("--overwrite", action="store_true", help="replace frames already in OUT")
    add_world_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from torchseam.sim.record import contact_sheet, write_sequence
    from torchseam.sim.sequence import SequenceSpec

    if args.frames < 1:
        raise TorchseamError(f"--frames must be at least 1, got {args.frames}")
    if args.start_mm is not None and not (math.isfinite(args.start_mm)
                                          and abs(args.start_mm) <= MAX_START_MM):
        raise TorchseamError(f"--start-mm must be an arc length within +-{MAX_START_MM:g} mm "
                             f"(the seam repeats every lap), got {args.start_mm}")
    cell, part, noise = load_cell(args.cell), load_part(args.part), load_noise(args.noise_model)
    try:
        level = noise.level(args.noise)
    except ValueError as e:
        raise TorchseamError(f"--noise: {e}") from None
    spec = SequenceSpec(n_frames=args.frames, level=level, seed=args.seed, start_mm=args.start_mm,
                        family=args.family)
    name = args.noise if args.noise in noise.levels else None
    try:
        truths = write_sequence(args.out, cell, part, noise, spec, name,
                                overwrite=args.overwrite, camera=args.camera)
    except KeyboardInterrupt:
        n = len(list(args.out.glob("[0-9]*.png")))
        print(f"torchseam simulate: {n} of {args.frames} frames written to {args.out} before the "
              "interrupt, with their labels.csv and meta.json", file=sys.stderr)
        raise
    visible = sum(t.visible for t in truths)
    print(f"wrote {len(truths)} {args.camera} frames to {args.out} (noise level {level:g}, "
          f"seed {args.seed}; seam visible in {visible})")
    if args.preview:
        pick = np.unique(np.linspace(0, len(truths) - 1, min(12, len(truths))).astype(int))
        imgs = [_read_frame(args.out / f"{i:05d}.png") for i in pick]
        caps = [f"#{i} {'flash ' if truths[i].flags.flash else ''}"
                f"{'burst' if truths[i].flags.burst else ''}" for i in pick]
        sheet = contact_sheet(imgs, [truths[i].uv for i in pick], caps)
        cv2.imwrite(str(args.out / "preview.png"), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        print(f"preview: {args.out / 'preview.png'}")
    return 0


def _read_frame(path: Path) -> np.ndarray:
    """A frame this command has just written (for the preview sheet)."""
    import cv2

    img = cv2.imread(str(path))
    if img is None:
        raise TorchseamError(f"{path}: cannot read the frame back for the preview")
    return img
