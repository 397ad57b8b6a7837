"""``torchseam train`` / ``python train/fit_tracker.py``: fit EAKF-STC on labelled sequences.

Single process::

    torchseam train --generate 16 --levels heavy,strike --frames 150 --epochs 12

Several processes (DistributedDataParallel over gloo; each takes a shard of every batch)::

    torchrun --nproc_per_node 2 train/fit_tracker.py --generate 16 --levels heavy,strike

Options come from ``configs/train.yaml`` (or ``--config``), then the command line. Each run
writes into its own folder, ``runs/<--name or the start time>/``; give its model to track, eval
or replay with ``--model``. ``--install`` is refused: EAKF-STC alone cannot replace the live
tracker's model, which ``torchseam train-live --install`` fits and installs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import platform
import re
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from torchseam.core.config import ConfigError
from torchseam.core.errors import DatasetError, TorchseamError
from torchseam.core.report import format_table
from torchseam.fit.config import FitConfig, load_fit_config, parse_seeds, train_yaml

if TYPE_CHECKING:  # torch: imported when the command runs, not by its parser (--help)
    from torchseam.fit.train import DistInfo, EpochRecord

__all__ = ["add_arguments", "main", "register", "run"]

log = logging.getLogger("torchseam.fit")

# option name -> FitConfig field (value None = not given on the command line)
_OPTS = ("data", "val_data", "val_fraction", "generate", "levels", "families", "seeds",
         "val_seeds",
         "val_levels",
         "frames", "max_frames", "cache", "roi", "margin", "fit", "epochs", "batch", "chunk",
         "lr", "huber", "clip", "seed", "threads", "dtype", "out", "model", "val_every",
         "lost_px", "test_levels", "test_seeds", "test_frames", "test_data")


def _defaults() -> dict[str, Any]:
    """The option defaults for ``--help``: FitConfig's, over them ``configs/train.yaml``'s
    (read leniently: a broken file is reported when the command runs, not here)."""
    d = FitConfig().to_dict()
    try:
        data = yaml.safe_load(train_yaml().read_text())
    except (OSError, yaml.YAMLError):
        data = None
    if isinstance(data, dict):
        d.update({k: v for k, v in data.items() if k in d})
    return d


def _shown(v: Any) -> str:
    if v is None:
        return "none"
    if isinstance(v, (list, tuple)):
        return ",".join(str(x) for x in v) or "none"
    return str(v)


def run_name_arg(text: str) -> str:
    """``--name``: a plain folder name under ``runs/``."""
    if not _NAME_RE.match(text) or text in (".", ".."):
        raise argparse.ArgumentTypeError(
            f"{text!r}: use a plain folder name (letters, digits, '.', '_', '-')")
    return text


_NAME_RE = re.compile(r"^[A-Za-z0-9._-]{1,100}$")
#: where a training run goes unless --out names a folder: RUNS_DIR/<--name or a timestamp>
RUNS_DIR = Path("runs")
#: the model file's name inside a run folder
RUN_MODEL = "eakf_stc.safetensors"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``torchseam train`` and ``train/fit_tracker.py`` (defaults: the config)."""
    d = _defaults()

    def dflt(key: str) -> str:
        return f"(default {_shown(d[key])})"

    p.add_argument("--config", type=Path, default=None,
                   help="options file (default configs/train.yaml"
                        " when present); the options below override it")
    g = p.add_argument_group("data")
    g.add_argument("--data", metavar="DIR",
                   help="labelled sequences: a dataset folder (frames + labels.csv) or a folder "
                        f"of them (e.g. your own recordings) {dflt('data')}")
    g.add_argument("--val-data", metavar="DIR", help="held-out sequences for validation "
                   "(default: --val-fraction of --data, or --val-seeds when generating)")
    g.add_argument("--val-fraction", type=float, metavar="F",
                   help=f"share of --data held out for validation {dflt('val_fraction')}")
    g.add_argument("--generate", type=int, metavar="N",
                   help="simulate N sequences per level into --cache and fit on them "
                        f"{dflt('generate')}")
    g.add_argument("--levels", metavar="L,L",
                   help=f"noise levels to simulate (names or 0..1) {dflt('levels')}")
    g.add_argument("--families", metavar="F,F",
                   help="appearance families to simulate (configs/noise.yaml; hold one out to "
                        f"score on it) {dflt('families')}")
    g.add_argument("--seeds", metavar="SPEC",
                   help=f"training seeds, e.g. 0-15 or 1,4,9 {dflt('seeds')}")
    g.add_argument("--val-seeds", metavar="SPEC",
                   help=f"validation seeds (simulated) {dflt('val_seeds')}")
    g.add_argument("--val-levels", metavar="L,L",
                   help="noise levels of the simulated validation set (empty: --levels) "
                        f"{dflt('val_levels')}")
    g.add_argument("--frames", type=int, metavar="N",
                   help=f"frames per simulated sequence {dflt('frames')}")
    g.add_argument("--max-frames", type=int, metavar="N",
                   help=f"use at most N frames per sequence (0: all) {dflt('max_frames')}")
    g.add_argument("--cache", metavar="DIR",
                   help=f"simulated sequences and crop cache {dflt('cache')}")
    g.add_argument("--roi", type=int, metavar="PX",
                   help=f"square crop side around each track {dflt('roi')}")
    g.add_argument("--margin", type=int, metavar="PX",
                   help=f"crop margin around the track {dflt('margin')}")
    o = p.add_argument_group("optimisation")
    o.add_argument("--fit", metavar="G,G", help="parameter groups to fit: lam,a,b,q,r,rho,guard"
                   f" and optionally alpha,sigma,beta {dflt('fit')}")
    o.add_argument("--epochs", type=int, metavar="N", help=f"passes over the data {dflt('epochs')}")
    o.add_argument("--batch", type=int, metavar="N",
                   help=f"sequences per step (global under torchrun) {dflt('batch')}")
    o.add_argument("--chunk", type=int, metavar="N",
                   help=f"truncated-BPTT length (frames) {dflt('chunk')}")
    o.add_argument("--lr", type=float, metavar="LR",
                   help=f"Adam learning rate on the raw parameters {dflt('lr')}")
    o.add_argument("--huber", type=float, metavar="PX", help=f"Huber delta {dflt('huber')}")
    o.add_argument("--clip", type=float, metavar="NORM",
                   help=f"gradient-norm clip (0: none) {dflt('clip')}")
    o.add_argument("--seed", type=int, metavar="N",
                   help=f"random seed: batch order, validation split {dflt('seed')}")
    o.add_argument("--threads", type=int, metavar="N",
                   help=f"torch threads per process {dflt('threads')}")
    o.add_argument("--dtype", choices=("float32", "float64"),
                   help=f"arithmetic of the fit {dflt('dtype')}")
    o.add_argument("--tracker", metavar="K=V,...",
                   help="starting-point TrackerConfig overrides, e.g. rho=0.05,crop=bilinear "
                        "(merged over the config file's tracker section; default: the paper's "
                        "values)")
    b = p.add_argument_group("output (a run folder; the model the trackers load is not "
                             "replaced: that is train-live --install)")
    b.add_argument("--name", type=run_name_arg, metavar="NAME",
                   help=f"run name: the run goes to {RUNS_DIR}/NAME/ (default: the start time, "
                        "YYYYmmdd-HHMMSS)")
    b.add_argument("--out", metavar="DIR",
                   help=f"the run folder instead of {RUNS_DIR}/NAME: checkpoint last.pt, "
                        "metrics.json, report.md, loss_curve.png and the model (default: "
                        f"{RUNS_DIR}/NAME)")
    b.add_argument("--model", metavar="FILE",
                   help=f"fitted model file to write (default RUN/{RUN_MODEL}); not the "
                        "model the trackers load (train-live --install replaces that)")
    b.add_argument("--install", action="store_true",
                   help="refused: EAKF-STC alone cannot replace the live tracker's model "
                        "(models/live_tracker.safetensors); `torchseam train-live --install` "
                        "fits and installs the live tracker")
    b.add_argument("--resume", nargs="?", const=True, default=False, metavar="CKPT",
                   help="continue the run named by --name or --out from its last.pt (or from "
                        "CKPT) (default: a new run)")
    b.add_argument("--val-every", type=int, metavar="N",
                   help=f"validate every N epochs {dflt('val_every')}")
    b.add_argument("--lost-px", type=float, metavar="PX",
                   help=f"error beyond which a frame counts as lost {dflt('lost_px')}")
    b.add_argument("--no-progress", action="store_true",
                   help="no progress bars (default: shown)")
    t = p.add_argument_group("held-out table (paper defaults vs fitted)")
    t.add_argument("--test-levels", metavar="L,L",
                   help=f"noise levels of the simulated test set {dflt('test_levels')}")
    t.add_argument("--test-seeds", metavar="SPEC",
                   help=f"seeds of the simulated test set {dflt('test_seeds')}")
    t.add_argument("--test-frames", type=int, metavar="N",
                   help=f"frames per test sequence {dflt('test_frames')}")
    t.add_argument("--test-data", metavar="DIR",
                   help=f"a labelled folder to test on instead {dflt('test_data')}")
    t.add_argument("--no-test", action="store_true",
                   help="skip the held-out table (default: printed when there is test data)")


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
    from torchseam.fit.data import find_sequences, generate_sequences
    from torchseam.fit.train import barrier

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
        kw: dict[str, Any] = {"progress": cfg.progress, "families": cfg.families}
        val_levels = cfg.val_levels or cfg.levels
        if info.main:
            train_dirs = generate_sequences(cfg.cache, cfg.levels, tr_seeds, cfg.frames, **kw)
            val_dirs = ([] if cfg.val_data else
                        generate_sequences(cfg.cache, val_levels, va_seeds, cfg.frames, **kw))
            if cfg.test and not cfg.test_data:
                test = generate_sequences(cfg.cache, cfg.test_levels, te_seeds,
                                          cfg.test_frames, **kw)
        barrier(info)
        if not info.main:  # the folders rank 0 made (generate reuses finished ones)
            train_dirs = generate_sequences(cfg.cache, cfg.levels, tr_seeds, cfg.frames,
                                            progress=False, families=cfg.families)
            val_dirs = ([] if cfg.val_data else
                        generate_sequences(cfg.cache, val_levels, va_seeds, cfg.frames,
                                           progress=False, families=cfg.families))
        desc["train"] = {"simulated": True, "levels": list(cfg.levels), "seeds": list(tr_seeds),
                         "frames": cfg.frames, "families": list(cfg.families)}
        if not cfg.val_data:
            desc["val"] = {"simulated": True, "levels": list(val_levels),
                           "families": list(cfg.families),
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
    from torchseam.fit.data import load_sequences
    from torchseam.fit.train import barrier

    kw: dict[str, Any] = {"roi": roi or cfg.roi, "margin": cfg.margin,
                          "max_frames": cfg.max_frames,
          "cache": cfg.cache}
    if info.main:
        s = load_sequences(dirs, progress=cfg.progress, **kw)
    barrier(info)
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


def _file_keys(config: Path | None) -> set[str]:
    """The options the options file sets (``--config``, else ``configs/train.yaml`` when
    present); :func:`load_fit_config` has read and checked it already."""
    p = Path(config) if config is not None else train_yaml()
    if config is None and not p.exists():
        return set()
    try:
        data = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError):
        return set()
    return set(data) if isinstance(data, dict) else set()


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve()
    except OSError:
        return False


def run_outputs(cfg: FitConfig, args: argparse.Namespace) -> FitConfig:
    """``cfg`` with its run folder (``out``) and model file (``model``) decided.

    The run folder: ``--out``, else the options file's ``out``, else ``runs/<--name>``
    (default name: the start time). The model: ``--model``, else the file's ``model``, else
    ``RUN/eakf_stc.safetensors``. The model the trackers load (``models/eakf_stc.safetensors``)
    is never the target: ``--install`` copies the run's model over it, keeping a backup. A run
    folder already holding a run is continued only with ``--resume``.

    Raises:
        TorchseamError: naming the option that asks for something refused.
    """
    name = getattr(args, "name", None)
    keys = _file_keys(getattr(args, "config", None))
    given_out = getattr(args, "out", None) is not None or "out" in keys
    if name is not None and getattr(args, "out", None) is not None:
        raise TorchseamError("--name and --out both name the run folder: give one of them")
    resume = getattr(args, "resume", False)
    if name is not None:
        out = RUNS_DIR / name
    elif given_out:
        out = Path(cfg.out)
    else:
        if resume is True:
            raise TorchseamError("--resume: name the run to continue with --name NAME (its "
                                 f"folder {RUNS_DIR}/NAME) or --out DIR")
        stamp = time.strftime("%Y%m%d-%H%M%S")
        out, n = RUNS_DIR / stamp, 2
        while out.exists():  # two runs started in the same second
            out, n = RUNS_DIR / f"{stamp}-{n}", n + 1
    model = (Path(cfg.model) if getattr(args, "model", None) is not None or "model" in keys
             else out / RUN_MODEL)
    from torchseam.fit import model_io

    shipped = model_io.DEFAULT_MODEL
    if getattr(args, "install", False) and not getattr(args, "live", False):
        raise TorchseamError(
            "--install: `torchseam train` fits EAKF-STC alone, which cannot replace the live "
            f"tracker's model ({shipped.name}); use `torchseam train-live --install`, or pass "
            "this run's model to track/eval/replay with --model")
    if _same_file(model, shipped):
        if not getattr(args, "install", False):
            where = "--model" if getattr(args, "model", None) is not None else "model"
            raise TorchseamError(
                f"{where} {model} is the model the trackers load: training writes into its run "
                f"folder ({out}); "
                + ("give --install to make the result the loaded model (the old one is kept "
                   "as a backup)" if getattr(args, "live", False) else
                   "give another --model, or fit the loaded model with "
                   "`torchseam train-live --install`"))
        model = out / RUN_MODEL  # --install copies it over, with a backup
    if out.exists() and not out.is_dir():
        raise TorchseamError(f"run folder {out} is a file")
    if not resume and ((out / "last.pt").exists() or model.exists()):
        held = out / "last.pt" if (out / "last.pt").exists() else model
        raise TorchseamError(f"{held} exists: that run would be overwritten; give another "
                             "--name (or --out), or --resume to continue it")
    return dataclasses.replace(cfg, out=str(out), model=str(model))


def run(args: argparse.Namespace) -> int:
    import torch.distributed as dist

    from torchseam.fit.train import init_distributed

    cfg = run_outputs(config_from_args(args), args)
    info = init_distributed()
    try:
        return _run(cfg, args.resume, info, install=getattr(args, "install", False))
    finally:
        if info.active and dist.is_initialized():
            dist.destroy_process_group()


def _run(cfg: FitConfig, resume: bool | str, info: DistInfo, install: bool = False) -> int:
    import cv2
    import torch

    from torchseam.fit import model_io
    from torchseam.fit.data import load_sequences
    from torchseam.fit.train import evaluate_folders, make_module, readable_params, train

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
    path = model_io.save_fitted(module, cfg.model, info_doc)
    (out / "metrics.json").write_text(json.dumps(info_doc, indent=1, default=float))
    (out / "report.md").write_text(report_markdown(info_doc))
    _loss_png(history, out / "loss_curve.png")
    print(f"\nwrote {path} ({time.perf_counter() - t0:.0f} s in all; history and metrics in "
          f"{out})")
    if install:
        dest, backup = model_io.install_model(path)
        print(f"installed {path} as {dest}"
              + (f" (the model it replaced: {backup})" if backup else ""))
    else:
        print(f"use it with --model {path} (track, eval, replay); to change the trackers' "
              "default model, fit the live tracker with `torchseam train-live --install`")
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
_TRACKER_FILES = ("config.py", "stc.py", "eakf.py", "fusion.py")


def _tracker_fingerprint() -> dict[str, str]:
    """Which tracker code the parameters were fitted for: the git commit (when in a checkout)
    and a hash of the module's source files ``torchseam/track/{config,stc,eakf,
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
    from torchseam.core.cliargs import OneLineParser

    p = OneLineParser(prog="fit_tracker", description=__doc__.splitlines()[0])
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
