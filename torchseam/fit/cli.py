"""``torchseam train`` / ``python train/fit_tracker.py``: fit EAKF-STC on labelled sequences.

Single process::

    torchseam train --generate 16 --levels heavy,strike --frames 150 --epochs 12

Several processes (DistributedDataParallel over gloo; each takes a shard of every batch)::

    torchrun --nproc_per_node 2 train/fit_tracker.py --generate 16 --levels heavy,strike

Options come from ``configs/train.yaml`` (or ``--config``), then the command line.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.distributed as dist
import yaml

from torchseam.core.config import ConfigError
from torchseam.core.errors import DatasetError, TorchseamError
from torchseam.core.report import format_table
from torchseam.fit.config import TRAIN_YAML, FitConfig, load_fit_config, parse_seeds
from torchseam.fit.data import find_sequences, generate_sequences, load_sequences
from torchseam.fit.model_io import save_fitted
from torchseam.fit.train import (
    DistInfo,
    EpochRecord,
    _barrier,
    evaluate_folders,
    init_distributed,
    make_module,
    readable_params,
    train,
)

__all__ = ["add_arguments", "main", "register", "run"]

log = logging.getLogger("torchseam.fit")

# option name -> FitConfig field (value None = not given on the command line)
_OPTS = ("data", "val_data", "val_fraction", "generate", "levels", "seeds", "val_seeds",
         "val_levels",
         "frames", "max_frames", "cache", "roi", "margin", "fit", "epochs", "batch", "chunk",
         "lr", "huber", "clip", "seed", "threads", "dtype", "out", "model", "val_every",
         "lost_px", "test_levels", "test_seeds", "test_frames", "test_data")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``torchseam train`` and ``train/fit_tracker.py`` (defaults: the config)."""
    p.add_argument("--config", type=Path, default=None,
                   help=f"options file (default {TRAIN_YAML.relative_to(TRAIN_YAML.parents[1])}"
                        " when present)")
    d = p.add_argument_group("data")
    d.add_argument("--data", metavar="DIR",
                   help="labelled sequences: a dataset folder (frames + labels.csv) or a folder "
                        "of them (e.g. your own recordings)")
    d.add_argument("--val-data", metavar="DIR", help="held-out sequences for validation "
                   "(default: --val-fraction of --data, or --val-seeds when generating)")
    d.add_argument("--val-fraction", type=float, metavar="F")
    d.add_argument("--generate", type=int, metavar="N",
                   help="simulate N sequences per level into --cache and fit on them")
    d.add_argument("--levels", metavar="L,L", help="noise levels to simulate (names or 0..1)")
    d.add_argument("--seeds", metavar="SPEC", help="training seeds, e.g. 0-15 or 1,4,9")
    d.add_argument("--val-seeds", metavar="SPEC", help="validation seeds (simulated)")
    d.add_argument("--val-levels", metavar="L,L",
                   help="noise levels of the simulated validation set (default: --levels)")
    d.add_argument("--frames", type=int, metavar="N", help="frames per simulated sequence")
    d.add_argument("--max-frames", type=int, metavar="N",
                   help="use at most N frames per sequence (0: all)")
    d.add_argument("--cache", metavar="DIR", help="simulated sequences and crop cache")
    d.add_argument("--roi", type=int, metavar="PX", help="square crop side around each track")
    d.add_argument("--margin", type=int, metavar="PX", help="crop margin around the track")
    o = p.add_argument_group("optimisation")
    o.add_argument("--fit", metavar="G,G", help="parameter groups to fit: lam,a,b,q,r,rho,guard"
                   " and optionally alpha,sigma,beta")
    o.add_argument("--epochs", type=int)
    o.add_argument("--batch", type=int, help="sequences per step (global under torchrun)")
    o.add_argument("--chunk", type=int, help="truncated-BPTT length (frames)")
    o.add_argument("--lr", type=float)
    o.add_argument("--huber", type=float, metavar="PX", help="Huber delta")
    o.add_argument("--clip", type=float, help="gradient-norm clip (0: none)")
    o.add_argument("--seed", type=int)
    o.add_argument("--threads", type=int, help="torch threads per process")
    o.add_argument("--dtype", choices=("float32", "float64"))
    o.add_argument("--tracker", metavar="K=V,...",
                   help="starting-point TrackerConfig overrides, e.g. rho=0.05,crop=bilinear "
                        "(merged over the config file's tracker section)")
    b = p.add_argument_group("output")
    b.add_argument("--out", metavar="DIR", help="checkpoints, history and metrics")
    b.add_argument("--model", metavar="FILE", help="fitted model (safetensors)")
    b.add_argument("--resume", nargs="?", const=True, default=False, metavar="CKPT",
                   help="continue from OUT/last.pt (or CKPT)")
    b.add_argument("--val-every", type=int, metavar="N")
    b.add_argument("--lost-px", type=float)
    b.add_argument("--no-progress", action="store_true", help="no progress bars")
    t = p.add_argument_group("held-out table (paper defaults vs fitted)")
    t.add_argument("--test-levels", metavar="L,L")
    t.add_argument("--test-seeds", metavar="SPEC")
    t.add_argument("--test-frames", type=int, metavar="N")
    t.add_argument("--test-data", metavar="DIR")
    t.add_argument("--no-test", action="store_true", help="skip the held-out table")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="fit the EAKF-STC parameters on labelled sequences",
        description="Fit EAKF-STC (lambda, a, b, Q, R, rho, drift guard; optionally alpha, "
                    "sigma) by gradient descent with truncated BPTT on labelled sequences "
                    "(simulated with --generate, or your own with --data). Multi-process: "
                    "torchrun --nproc_per_node N train/fit_tracker.py ...")
    add_arguments(p)
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace) -> FitConfig:
    over: dict[str, Any] = {k: getattr(args, k, None) for k in _OPTS}
    if getattr(args, "no_progress", False):
        over["progress"] = False
    if getattr(args, "no_test", False):
        over["test"] = False
    cfg = load_fit_config(args.config, over)
    if getattr(args, "tracker", None):
        merged = {**cfg.tracker, **_parse_pairs(args.tracker)}
        cfg = load_fit_config(args.config, {**over, "tracker": merged})
    return cfg


def _parse_pairs(text: str) -> dict[str, Any]:
    """``"rho=0.05,window=[48,48]"`` -> {"rho": 0.05, "window": [48, 48]} (YAML values)."""
    out: dict[str, Any] = {}
    depth, cur, parts = 0, "", []
    for ch in text:  # split on commas outside brackets
        depth += ch in "[{"
        depth -= ch in "]}"
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    for part in parts:
        if not part.strip():
            continue
        key, sep, val = part.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--tracker {text!r}: expected KEY=VALUE pairs, got {part!r}")
        try:
            out[key.strip()] = yaml.safe_load(val)
        except yaml.YAMLError:
            raise ConfigError(f"--tracker: {key.strip()}: cannot read value {val!r}") from None
    return out


def _seeds(cfg: FitConfig, spec: str, name: str, n: int | None = None) -> tuple[int, ...]:
    seeds = parse_seeds(spec, name)
    if n is not None:
        if len(seeds) < n:
            raise TorchseamError(f"--generate {n}: --{name.replace('_', '-')} {spec!r} names "
                                 f"only {len(seeds)} seeds")
        seeds = seeds[:n]
    return seeds


def _resolve(cfg: FitConfig, info: DistInfo
             ) -> tuple[list[Path], list[Path], list[Path], dict[str, Any]]:
    """Training, validation and test folders, plus a description for the model file."""
    desc: dict[str, Any] = {}
    test: list[Path] = []
    if cfg.generate > 0:
        tr_seeds = _seeds(cfg, cfg.seeds, "seeds", cfg.generate)
        va_seeds = _seeds(cfg, cfg.val_seeds, "val_seeds")
        te_seeds = _seeds(cfg, cfg.test_seeds, "test_seeds")
        overlap = (set(tr_seeds) & set(va_seeds)) | (set(tr_seeds) & set(te_seeds))
        if overlap:
            raise TorchseamError(f"seeds {sorted(overlap)} are used for training and for "
                                 "validation or testing: choose disjoint seeds")
        kw = {"progress": cfg.progress}
        val_levels = cfg.val_levels or cfg.levels
        if info.main:
            train_dirs = generate_sequences(cfg.cache, cfg.levels, tr_seeds, cfg.frames, **kw)
            val_dirs = ([] if cfg.val_data else
                        generate_sequences(cfg.cache, val_levels, va_seeds, cfg.frames, **kw))
            if cfg.test and not cfg.test_data:
                test = generate_sequences(cfg.cache, cfg.test_levels, te_seeds,
                                          cfg.test_frames, **kw)
        _barrier(info)
        if not info.main:  # the folders rank 0 made (generate reuses finished ones)
            train_dirs = generate_sequences(cfg.cache, cfg.levels, tr_seeds, cfg.frames,
                                            progress=False)
            val_dirs = ([] if cfg.val_data else
                        generate_sequences(cfg.cache, val_levels, va_seeds, cfg.frames,
                                           progress=False))
        desc["train"] = {"simulated": True, "levels": list(cfg.levels), "seeds": list(tr_seeds),
                         "frames": cfg.frames}
        if not cfg.val_data:
            desc["val"] = {"simulated": True, "levels": list(val_levels),
                           "seeds": list(va_seeds), "frames": cfg.frames}
        if test:
            desc["test"] = {"simulated": True, "levels": list(cfg.test_levels),
                            "seeds": list(te_seeds), "frames": cfg.test_frames}
    elif cfg.data:
        all_dirs = find_sequences(cfg.data)
        if cfg.val_data:
            train_dirs, val_dirs = all_dirs, []
        else:
            n_val = int(round(cfg.val_fraction * len(all_dirs)))
            if cfg.val_fraction > 0 and len(all_dirs) >= 2:
                n_val = min(max(n_val, 1), len(all_dirs) - 1)
            else:
                n_val = 0
            perm = np.random.default_rng(cfg.seed).permutation(len(all_dirs))
            val_dirs = [all_dirs[i] for i in sorted(perm[:n_val])]
            train_dirs = [all_dirs[i] for i in sorted(perm[n_val:])]
        desc["train"] = {"data": cfg.data, "sequences": [str(d) for d in train_dirs]}
        if val_dirs:
            desc["val"] = {"data": cfg.data, "sequences": [str(d) for d in val_dirs]}
    else:
        raise DatasetError("no training data: give --data DIR (labelled sequences: frames "
                           "00000.png ... + labels.csv) or --generate N (simulate N per level)")
    if cfg.val_data:
        val_dirs = find_sequences(cfg.val_data)
        desc["val"] = {"data": cfg.val_data, "sequences": [str(d) for d in val_dirs]}
    if cfg.test and cfg.test_data:
        test = find_sequences(cfg.test_data)
        desc["test"] = {"data": cfg.test_data, "sequences": [str(d) for d in test]}
    return train_dirs, val_dirs, test, desc


def _load(dirs: list[Path], cfg: FitConfig, info: DistInfo, roi: int | None = None):
    kw = {"roi": roi or cfg.roi, "margin": cfg.margin, "max_frames": cfg.max_frames,
          "cache": cfg.cache}
    if info.main:
        s = load_sequences(dirs, progress=cfg.progress, **kw)
    _barrier(info)
    if not info.main:
        s = load_sequences(dirs, progress=False, build=False, **kw)
    return s


def test_table(rows: list[dict[str, Any]]) -> str:
    return format_table(["noise", "parameters", "frames", "RMSE px", "max px", "> 5 px %",
                         "lost %"],
                        [[r["group"], r["model"], r["n"], r["rmse"], r["max"], r["pct_gt5"],
                          r["pct_lost"]] for r in rows])


def history_table(history: list[EpochRecord]) -> str:
    groups = sorted({g for h in history if h.val for g in h.val})
    heads = ["epoch", "train loss", "val loss", *(f"{g} RMSE" for g in groups), "s"]
    rows = []
    for h in history:
        v = h.val or {}
        rows.append([h.epoch, h.loss if h.loss is not None else "-",
                     h.val_loss if h.val_loss is not None else "-",
                     *(v[g]["rmse"] if g in v else "-" for g in groups), h.seconds])
    return format_table(heads, rows)


def _loss_png(history: list[EpochRecord], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        return
    fig, ax = plt.subplots(figsize=(4.2, 2.8), dpi=100)
    tr = [(h.epoch, h.loss) for h in history if h.loss is not None]
    if tr:
        ax.plot(*zip(*tr, strict=True), "o-", label="train")
    vv = [(h.epoch, h.val_loss) for h in history if h.val_loss is not None]
    if vv:
        ax.plot(*zip(*vv, strict=True), "s-", label="validation")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("Huber loss (px)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    info = init_distributed()
    try:
        return _run(cfg, args.resume, info)
    finally:
        if info.active and dist.is_initialized():
            dist.destroy_process_group()


def _run(cfg: FitConfig, resume: bool | str, info: DistInfo) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(cfg.threads)
    cv2.setNumThreads(1)
    say = print if info.main else (lambda *a, **k: None)
    t0 = time.perf_counter()
    train_dirs, val_dirs, test_dirs, desc = _resolve(cfg, info)
    train_set = _load(train_dirs, cfg, info)
    val_set = None
    if val_dirs and info.main:  # only rank 0 validates
        val_set = load_sequences(val_dirs, roi=train_set.roi, margin=cfg.margin,
                                 max_frames=cfg.max_frames, cache=cfg.cache,
                                 progress=cfg.progress)
    say(f"train: {train_set.describe()}")
    if val_set is not None:
        say(f"validation: {val_set.describe()}")
    say(f"processes: {info.world}, torch threads each: {torch.get_num_threads()}, "
        f"fitting {', '.join(cfg.fit)}")
    module, history = train(cfg, train_set, val_set, resume=resume, info=info)
    if not info.main:
        return 0
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    print("\n" + history_table(history))
    rows: list[dict[str, Any]] = []
    if test_dirs:
        module.eval()
        base = make_module(cfg.tracker_config(), cfg.dtype).eval()
        print(f"\nheld-out table: {len(test_dirs)} sequences, full frames")
        rows = evaluate_folders({"paper defaults": base, "fitted": module}, test_dirs,
                                batch=max(1, min(cfg.batch, 8)), lost_px=cfg.lost_px,
                                progress=cfg.progress)
        print(test_table(rows))
        print(f"errors over the labelled frames after the start; lost = no point or "
              f"> {cfg.lost_px:g} px off")
    elif cfg.test:
        say("(no held-out table: give --test-data DIR, or --generate to simulate one)")
    per_epoch = [h.seconds for h in history if h.loss is not None]
    info_doc = {"data": desc, "config": cfg.to_dict(), "epochs": len(history),
                "history": [{"epoch": h.epoch, "loss": h.loss, "val_loss": h.val_loss,
                             "val": h.val, "seconds": h.seconds} for h in history],
                "params": readable_params(module),
                "start_params": readable_params(make_module(cfg.tracker_config())),
                "test": rows,
                "processes": info.world, "machine": platform.machine(),
                "tracker_source": _tracker_fingerprint(),
                "seconds_per_epoch": float(np.median(per_epoch)) if per_epoch else None,
                "command": " ".join(sys.argv)}
    path = save_fitted(module, cfg.model, info_doc)
    (out / "metrics.json").write_text(json.dumps(info_doc, indent=1, default=float))
    (out / "report.md").write_text(report_markdown(info_doc))
    _loss_png(history, out / "loss_curve.png")
    print(f"\nwrote {path} ({time.perf_counter() - t0:.0f} s in all; history and metrics in "
          f"{out})")
    return 0


def _md_table(headers: list[str], rows: list[list[Any]]) -> str:
    def cell(x: Any) -> str:
        if isinstance(x, float):
            return "-" if not np.isfinite(x) else f"{x:.3f}" if abs(x) < 100 else f"{x:.0f}"
        return str(x)

    lines = ["| " + " | ".join(headers) + " |", "|" + " --- |" * len(headers)]
    lines += ["| " + " | ".join(cell(x) for x in r) + " |" for r in rows]
    return "\n".join(lines)


def report_markdown(doc: dict[str, Any]) -> str:
    """The run as Markdown: data, loss curve, parameters, held-out table (``report.md``)."""
    out = [f"Command: `{doc.get('command', '')}`", ""]
    for k, v in (doc.get("data") or {}).items():
        out.append(f"- {k}: {json.dumps(v)}")
    hist = doc.get("history") or []
    groups = sorted({g for h in hist if h.get("val") for g in h["val"]})
    heads = ["epoch", "train loss", "val loss"] + [f"{g} RMSE / max / lost %" for g in groups]
    rows = []
    for h in hist:
        v = h.get("val") or {}
        rows.append([h["epoch"], h["loss"] if h["loss"] is not None else "-",
                     h["val_loss"] if h["val_loss"] is not None else "-"]
                    + [f"{v[g]['rmse']:.2f} / {v[g]['max']:.1f} / {v[g]['pct_lost']:.1f}"
                       if g in v else "-" for g in groups])
    out += ["", "Loss curve (mean Huber loss per labelled coordinate, px):", "",
            _md_table(heads, rows)]
    params = doc.get("params") or {}
    start = doc.get("start_params") or {}
    if params:
        prow = [[k, ", ".join(f"{x:.4g}" for x in start.get(k, [])) or "-",
                 ", ".join(f"{x:.4g}" for x in v)] for k, v in params.items()]
        out += ["", "Parameters (natural units; R per axis: position, displacement):", "",
                _md_table(["parameter", "start", "fitted"], prow)]
    test = doc.get("test") or []
    if test:
        out += ["", "Held-out sequences (full frames):", "",
                _md_table(["noise", "parameters", "frames", "RMSE px", "max px", "> 5 px %",
                           "lost %"],
                          [[r["group"], r["model"], r["n"], r["rmse"], r["max"], r["pct_gt5"],
                            r["pct_lost"]] for r in test])]
    return "\n".join(out) + "\n"


#: the files that define the EAKF-STC module (and so what its parameters mean)
_TRACKER_FILES = ("_checks.py", "config.py", "stc.py", "eakf.py", "fusion.py")


def _tracker_fingerprint() -> dict[str, str]:
    """Which tracker code the parameters were fitted for: the git commit (when in a checkout)
    and a hash of the module's source files ``torchseam/track/{_checks,config,stc,eakf,
    fusion}.py`` (a changed tracker needs a new fit)."""
    import hashlib
    import subprocess

    import torchseam.track as trk

    root = Path(trk.__file__).resolve().parent
    h = hashlib.sha1()
    for name in _TRACKER_FILES:
        f = root / name
        if f.is_file():
            h.update(name.encode() + f.read_bytes())
    out = {"sha1": h.hexdigest()[:16]}
    try:
        out["git"] = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                                    capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``train/fit_tracker.py`` (errors become one-line messages)."""
    p = argparse.ArgumentParser(prog="fit_tracker", description=__doc__.splitlines()[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except TorchseamError as e:
        print(f"fit_tracker: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fit_tracker: interrupted", file=sys.stderr)
        return 130
