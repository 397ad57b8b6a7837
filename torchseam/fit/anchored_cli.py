"""``torchseam train-live``: fit the live tracker end to end (see :mod:`torchseam.fit.anchored`).

    torchseam train-live --name live-1            # configs/train_live.yaml, into runs/live-1/
    torchseam train-live --name live-1 --install  # ... and make it the model the trackers load
    torchseam train-live --families sim,wide,thin --name no-smoke   # hold a family out
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from torchseam.core.cliargs import model_arg
from torchseam.core.errors import TorchseamError

HELP = "fit the live tracker (EAKF-STC and the fusion) end to end on full sequences"


def _names(text: str) -> tuple[str, ...]:
    out = tuple(t.strip() for t in text.split(",") if t.strip())
    if not out:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a comma-separated list")
    return out


def _seeds(text: str) -> tuple[int, ...]:
    from torchseam.fit.config import parse_seeds

    try:
        return parse_seeds(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _int_at_least(lo: int):  # noqa: ANN202 - an argparse type
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"{v}: expected at least {lo}")
        return v
    return parse


def register(sub: argparse._SubParsersAction) -> None:
    from torchseam.fit.cli import run_name_arg

    p = sub.add_parser("train-live", help=HELP, description=HELP + ". Defaults: "
                       "configs/train_live.yaml; each option below overrides its field.")
    p.add_argument("--config", metavar="FILE",
                   help="options file (default: configs/train_live.yaml)")
    p.add_argument("--families", type=_names, metavar="A,B",
                   help="appearance families to fit on (default: the file's, sim,wide,thin,"
                        "smoke; glint held out)")
    p.add_argument("--levels", type=_names, metavar="A,B",
                   help="noise levels (clean, light, strike, heavy, beyond; default: the "
                        "file's)")
    p.add_argument("--seeds", type=_seeds, metavar="S",
                   help="training seeds, e.g. 0-1 (default: the file's, 0)")
    p.add_argument("--val-seeds", type=_seeds, metavar="S",
                   help="validation seeds (default: the file's, 500-501)")
    p.add_argument("--frames", type=_int_at_least(30), metavar="N",
                   help="frames per sequence (default: the file's, 300)")
    p.add_argument("--epochs", type=_int_at_least(0), metavar="N",
                   help="epochs (0: the start only; default: the file's)")
    p.add_argument("--data", action="append", metavar="DIR",
                   help="your labelled recordings to fit on instead of simulated sequences: "
                        "a dataset folder (frames 00000.png ... and labels.csv) or a folder "
                        "of them; repeatable (default: none, simulate)")
    p.add_argument("--val-data", action="append", metavar="DIR",
                   help="labelled recordings to select the epoch on (needed with --data; "
                        "other recordings than --data's; default: none)")
    p.add_argument("--start", type=model_arg, metavar="FILE",
                   help="model file to start from (live tracker or EAKF-STC alone; default: "
                        "models/eakf_stc.safetensors, the fusion from configs/anchor.yaml)")
    p.add_argument("--name", type=run_name_arg, metavar="NAME",
                   help="run folder runs/NAME (default: the start time)")
    p.add_argument("--install", action="store_true",
                   help="make the fitted model the one the trackers load "
                        "(models/live_tracker.safetensors; the old one kept as a backup; "
                        "default: off)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch  # here, not at the top: the parser (--help) needs no torch

    from torchseam.core.config import FAMILY_NAMES, load_cell, load_noise, load_part
    from torchseam.fit import model_io
    from torchseam.fit.anchored import (
        fit_anchored,
        load_anchored_fit_config,
        load_set,
        simulate_set,
    )
    from torchseam.fit.cli import RUNS_DIR
    from torchseam.fit.train import make_module
    from torchseam.track.anchored import AnchoredModel, fitted_eakf_stc, load_anchor_config
    from torchseam.vision.tipm import load_tipm

    cfg = load_anchored_fit_config(args.config)
    over = {k: getattr(args, k) for k in ("families", "levels", "seeds", "val_seeds",
                                          "frames", "epochs")
            if getattr(args, k, None) is not None}
    cfg = dataclasses.replace(cfg, **over)
    noise = load_noise()
    unknown = [f for f in cfg.families if f not in FAMILY_NAMES]
    if unknown:
        raise TorchseamError(f"--families: unknown family {unknown[0]!r} (configs/noise.yaml "
                             f"has {', '.join(FAMILY_NAMES)})")
    out = RUNS_DIR / (args.name or time.strftime("%Y%m%d-%H%M%S"))
    if (out / "live_tracker.safetensors").exists():
        raise TorchseamError(f"{out}/live_tracker.safetensors exists: give another --name")
    torch.set_num_threads(cfg.threads)
    dtype = getattr(torch, cfg.dtype)
    start = Path(args.start) if args.start else model_io.MODEL_DIR / "eakf_stc.safetensors"
    base = fitted_eakf_stc(model_path=start)
    # reg and anchor are STC extensions that exist only when switched on (> 0): a fit of
    # either needs a start that has it (tracker: {reg: > 0} and {anchor: > 0})
    switched = {"reg": base.config.reg, "anchor": base.config.anchor}
    off = [g for g, v in switched.items() if g in cfg.fit and not v]
    if off:
        raise TorchseamError(
            f"--start {start}: its STC has {' and '.join(off)} switched off (0), which the fit "
            f"frees (train_live.yaml fit: {', '.join(cfg.fit)}): fit the start with `torchseam "
            "train --tracker reg=20,anchor=0.3` (the shipped start's values), or leave "
            f"{', '.join(off)} out of fit: in your copy of train_live.yaml")
    eakf = make_module(base.config, dtype)
    model_io.load_fitted(eakf, start)
    live = AnchoredModel(eakf, load_anchor_config(), learnable=True).to(dtype)
    if model_io.read_model(start)[1]["format"] == model_io.LIVE_FORMAT:
        model_io.load_fitted(live, start)
    if bool(args.data) != bool(args.val_data):
        raise TorchseamError("--data and --val-data go together: a fit on your recordings "
                             "selects its epoch on other recordings of yours")
    cell, part, tipm = load_cell(), load_part(), load_tipm()
    say = print
    if args.data:
        say("reading the recordings ...", flush=True)
        train, val = load_set(args.data, tipm=tipm), load_set(args.val_data, tipm=tipm)
    else:
        say(f"simulating {len(cfg.families) * len(cfg.levels) * len(cfg.seeds)} training "
            f"and {len(cfg.families) * len(cfg.val_levels) * len(cfg.val_seeds)} validation "
            f"sequences of {cfg.frames} frames ...", flush=True)
        train = simulate_set(cell, part, noise, cfg.families, cfg.levels, cfg.seeds,
                             cfg.frames, cfg.hide_frames, tipm=tipm)
        val = simulate_set(cell, part, noise, cfg.families, cfg.val_levels, cfg.val_seeds,
                           cfg.frames, cfg.hide_frames, tipm=tipm)
    data: dict[str, object] = (
        {"train": {"recordings": [str(d) for d in args.data], "families": ["recorded"]},
         "val": {"recordings": [str(d) for d in args.val_data]}} if args.data else
        {"train": {"families": list(cfg.families), "levels": list(cfg.levels),
                   "seeds": list(cfg.seeds), "frames": cfg.frames},
         "val": {"families": list(cfg.families), "levels": list(cfg.val_levels),
                 "seeds": list(cfg.val_seeds)}})
    info = {"data": data,
            "start": str(start), "command": "torchseam train-live " + " ".join(
                f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()
                if k in over)}
    metrics = fit_anchored(live, train, val, cfg, out, info,
                       say=lambda s: print(s, flush=True), tipm=tipm)
    path = out / "live_tracker.safetensors"
    print(f"kept epoch {metrics['best_epoch']}; model {path}")
    if args.install:
        dest, backup = model_io.install_model(path)
        print(f"installed {path} as {dest}" + (f" (the old one kept as {backup})"
                                                if backup else ""))
    return 0
