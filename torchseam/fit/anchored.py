"""Fitting the live tracker end to end: EAKF-STC and the fusion's values
(:class:`~torchseam.track.anchored.AnchoredModel`) by gradient descent on full-length labelled
sequences of several appearance families.

One epoch: the training sequences, B at a time, tracked from their frame-0 label exactly as the
live loop tracks (TIPM's windowed fixes, the gates, re-anchoring, the whole-frame search while
coasting); truncated back-propagation through time in chunks of ``chunk`` frames: after each
chunk the Huber loss between the fused and the true points is back-propagated, the optimiser
steps, and the state, cut from the graph, carries on with the new values. Whole sequences
(300 frames and more), so long heavy-arc and glare stretches are in the loss. The gates and
thresholds are hard forward and straight-through backward
(:class:`~torchseam.track.anchored.TorchOps`).
After each epoch the validation sequences (other seeds) are tracked without gradients; the
values of the epoch with the lowest validation loss are kept (epoch 0, the starting point,
competes). Nothing is changed by hand afterwards.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchseam.core.config import (
    CellConfig,
    NoiseConfig,
    PartConfig,
    config_field,
    config_path,
    load_config,
)
from torchseam.core.report import error_stats
from torchseam.fit.config import PARAM_GROUPS
from torchseam.fit.model_io import FitError, save_fitted
from torchseam.sim.sequence import SequenceSpec, simulate_labelled
from torchseam.sim.variants import hide_corner
from torchseam.track.anchored import AnchoredModel
from torchseam.vision.tipm import Tipm, find_view, red_response

__all__ = ["BEYOND", "AnchoredFitConfig", "AnchoredSequence", "fit_anchored",
           "load_anchored_fit_config", "load_set", "simulate_set", "track_set"]

log = logging.getLogger("torchseam.fit")

#: a level name: heavy arc plus glare hiding the corner for tens of frames (randomly placed)
BEYOND = "beyond"


@dataclass(frozen=True)
class AnchoredFitConfig:
    """Options of ``torchseam train-live`` (``configs/train_live.yaml``)."""

    families: tuple[str, ...] = config_field()
    levels: tuple[str, ...] = config_field()
    seeds: tuple[int, ...] = config_field()
    val_seeds: tuple[int, ...] = config_field()
    val_levels: tuple[str, ...] = config_field()
    frames: int = config_field(lo=30)
    hide_frames: tuple[int, ...] = config_field()
    fit: tuple[str, ...] = config_field()
    epochs: int = config_field(lo=0)
    batch: int = config_field(lo=1)
    chunk: int = config_field(lo=1)
    lr: float = config_field(lo=0.0, lo_open=True)
    huber: float = config_field(lo=0.0, lo_open=True)
    clip: float = config_field(lo=0.0)
    lost_px: float = config_field(lo=0.0, lo_open=True)
    threads: int = config_field(lo=1)
    dtype: str = config_field()


def load_anchored_fit_config(path: str | Path | None = None) -> AnchoredFitConfig:
    """:class:`AnchoredFitConfig` from ``path`` (default ``configs/train_live.yaml``)."""
    return load_config(AnchoredFitConfig, path or config_path("train_live.yaml"))


@dataclass
class AnchoredSequence:
    """One labelled sequence in memory: ``frames`` (T of (H, W, 3) uint8), ``labels`` (T, 2),
    ``group`` (``family/level``), ``hidden`` (T,) frames with the corner hidden."""

    frames: list[np.ndarray]
    labels: np.ndarray
    group: str
    hidden: np.ndarray


def simulate_set(cell: CellConfig, part: PartConfig, noise: NoiseConfig,
                 families: Sequence[str], levels: Sequence[str], seeds: Sequence[int],
                 n_frames: int, hide_frames: Sequence[int] = (30, 60),
                 progress: Callable[[str], None] | None = None, *, tipm: Tipm
                 ) -> list[AnchoredSequence]:
    """One sequence per (family, level, seed), simulated in memory and read in the view the
    live loop finds on its first frame (:func:`~torchseam.vision.tipm.find_view` with
    ``tipm``). Level
    ``beyond``: heavy arc plus the corner hidden under glare for each of ``hide_frames``
    frames, at places drawn from the seed (the benchmark's places are fixed: a fit must not
    learn them)."""
    out = []
    for fam in families:
        for name in levels:
            try:
                level = noise.level("heavy" if name == BEYOND else name)
            except ValueError as e:
                raise FitError(f"levels: {e}") from None
            for s in seeds:
                spec = SequenceSpec(n_frames=n_frames, level=level, seed=s, family=fam)
                frames, labels, _ = simulate_labelled(cell, part, noise, spec)
                hidden = np.zeros(len(frames), bool)
                if name == BEYOND:
                    rng = np.random.default_rng(10_000 + s)
                    n = len(frames)
                    stretches = []
                    for k, length in enumerate(hide_frames):
                        lo, hi = 0.15 + 0.45 * k, 0.45 + 0.45 * k
                        start = float(rng.uniform(lo, max(lo, min(hi, 1 - (length + 5) / n))))
                        stretches.append((start, int(length)))
                    frames, hidden = hide_corner(frames, labels, tuple(stretches))
                # the view the live loop reads this camera in (cell config `auto`): found on
                # the first, clean frame, e.g. the brightness where the stripe is so bright
                # that its red excess is gone (rows: the labels stay as they are)
                view = find_view(frames[0], tipm, "rows", "auto")
                if view is not None and view.response != "red":
                    frames = [view.frame(f) for f in frames]
                out.append(AnchoredSequence(frames, labels, f"{fam}/{name}", hidden))
                if progress:
                    progress(f"simulated {fam}/{name} seed {s}")
    return out


def load_set(roots: Sequence[str | Path], progress: Callable[[str], None] | None = None, *,
             tipm: Tipm) -> list[AnchoredSequence]:
    """Labelled recordings (a dataset folder, or a folder of them: frames ``00000.png`` ... and
    ``labels.csv``) as sequences in the view the live loop finds on their first frame (with
    ``tipm``); each is
    tracked from its first labelled frame, frames without a label count in no loss."""
    from torchseam.core.dataset import Dataset, check_frame
    from torchseam.fit.data import find_sequences

    out = []
    for root in roots:
        for d in find_sequences(root):
            ds = Dataset.open(d, require_labels=True)
            assert ds.labels is not None  # require_labels
            first = int(np.argmax(ds.labelled))
            frames = [check_frame(ds.read(i), name=f"{d} frame {i}")
                      for i in range(first, len(ds))]
            view = find_view(frames[0], tipm, "rows", "auto")
            if view is None:
                raise FitError(f"{d}: no stripe corner on frame {first}, the first labelled "
                               "one (the fit starts each recording there)")
            frames = [view.frame(f) for f in frames]
            out.append(AnchoredSequence(frames, ds.labels[first:], d.name,
                                    np.zeros(len(frames), bool)))
            if progress:
                progress(f"read {d} ({len(frames)} frames)")
    return out


def _grey(frames: Sequence[np.ndarray]) -> Tensor:
    return torch.from_numpy(np.stack([red_response(f) for f in frames]))


def track_set(module: AnchoredModel, seqs: Sequence[AnchoredSequence], batch: int,
              chunk: int = 0, huber: float = 2.0,
              opt: torch.optim.Optimizer | None = None, clip: float = 0.0, *, tipm: Tipm
              ) -> tuple[float, list[np.ndarray], list[list[int]]]:
    """Track ``seqs`` (equal lengths within a batch) from their frame-0 labels, B at a time
    (``tipm``: the fixes' TIPM). With ``opt``: truncated BPTT, an optimiser step per ``chunk``
    frames.

    Returns:
        (mean Huber per coordinate, per-sequence fused points (T, 2), statuses).
    """
    dtype = module.eakf_stc.eakf.dt.dtype
    hsum, hn = 0.0, 0
    uvs: list[np.ndarray] = []
    stats: list[list[int]] = []
    params = [p for p in module.parameters() if p.requires_grad]
    for b0 in range(0, len(seqs), batch):
        group = list(seqs[b0:b0 + batch])
        T = min(len(s.frames) for s in group)
        labels = torch.from_numpy(np.stack([s.labels[:T] for s in group])).to(dtype)
        with torch.set_grad_enabled(opt is not None):
            state = module.init_state([s.frames[0] for s in group],
                                      _grey([s.frames[0] for s in group]), labels[:, 0],
                                      tipm=tipm)
            out = [labels[:, 0].detach().numpy().astype(float)]
            st: list[list[int]] = [[0] * len(group)]
            loss = labels.new_zeros(())
            n_in_chunk = 0
            for t in range(1, T):
                frames = [s.frames[t] for s in group]
                state, x, status = module.step_state(state, frames, _grey(frames))
                lab = labels[:, t]
                seen = torch.isfinite(lab)  # an unlabelled frame counts in no loss
                err = F.huber_loss(torch.where(seen, x, lab.nan_to_num()), lab.nan_to_num(),
                                   reduction="sum", delta=huber)
                loss = loss + err
                hsum += float(err.detach())
                hn += int(seen.sum())
                n_in_chunk += int(seen.sum())
                out.append(x.detach().to(torch.float64).numpy())
                st.append(status)
                if opt is not None and n_in_chunk and (t % chunk == 0 or t == T - 1):
                    opt.zero_grad(set_to_none=True)
                    (loss / n_in_chunk).backward()
                    if clip > 0:
                        torch.nn.utils.clip_grad_norm_(params, clip)
                    opt.step()
                    state = module.detach(state)
                    loss, n_in_chunk = labels.new_zeros(()), 0
        arr = np.stack(out, axis=1)
        for j in range(len(group)):
            uvs.append(arr[j])
            stats.append([row[j] for row in st])
    return hsum / max(hn, 1), uvs, stats


def errors_by_group(seqs: Sequence[AnchoredSequence], uvs: Sequence[np.ndarray],
                    lost_px: float) -> dict[str, dict[str, float]]:
    """error_stats per group over frames 1.. of each sequence."""
    errs: dict[str, list[np.ndarray]] = {}
    for s, uv in zip(seqs, uvs, strict=True):
        lab = s.labels[1:len(uv)]
        e = np.linalg.norm(uv[1:] - lab, axis=1)
        e[~np.isfinite(e)] = np.nan  # a diverged point counts as lost ...
        errs.setdefault(s.group, []).append(e[np.isfinite(lab).all(axis=1)])  # ... unlabelled: none
    return {g: error_stats(np.concatenate(v), lost_px) for g, v in errs.items()}


def _select(module: AnchoredModel, groups: Sequence[str]) -> list[str]:
    """Free EAKF-STC's parameters of ``groups`` (:data:`PARAM_GROUPS`) and every fusion
    value (``fusion``); freeze the rest."""
    names: set[str] = set()
    params = dict(module.named_parameters())
    for g in groups:
        if g == "fusion":
            names |= {n for n in params if n.startswith("fusion.")}
            continue
        if g not in PARAM_GROUPS:
            raise FitError(f"fit: unknown group {g!r}: use fusion or one of "
                           f"{', '.join(PARAM_GROUPS)}")
        for pat in PARAM_GROUPS[g]:
            full = "eakf_stc." + pat
            hit = ({n for n in params if n.startswith(full)} if pat.endswith(".")
                   else {full} & set(params))
            if not hit:
                raise FitError(f"fit: the tracker has no parameter {pat!r} (group {g!r})")
            names |= hit
    for n, p in params.items():
        p.requires_grad_(n in names)
    return sorted(names)


def readable(module: AnchoredModel) -> dict[str, Any]:
    """The fusion's values and EAKF-STC's scalars in their units (for logs and the report)."""
    out: dict[str, Any] = {f"fusion.{k}": round(v, 6)
                           for k, v in module.fusion.values().items()}
    e = module.eakf_stc
    for name, val in (("lam", e.eakf.lam), ("a", e.eakf.a), ("b", e.eakf.b), ("rho", e.stc.rho),
                      ("reg", e.stc.reg), ("anchor", e.stc.anchor)):
        v = val.detach().reshape(-1)
        out[f"eakf_stc.{name}"] = [round(float(x), 6) for x in v] if v.numel() > 1 else round(
            float(v), 6)
    return out


def fit_anchored(module: AnchoredModel, train: Sequence[AnchoredSequence],
                 val: Sequence[AnchoredSequence], cfg: AnchoredFitConfig, out: Path,
                 info: dict[str, Any], say: Callable[[str], None] = print, *,
                 tipm: Tipm) -> dict[str, Any]:
    """Fit ``module`` (built learnable) on ``train``, select on ``val`` (``tipm``: the fixes'
    TIPM, the one the live loop runs); write ``out/live_tracker.safetensors`` and
    ``out/metrics.json``.

    Returns:
        The metrics (history per epoch, the kept epoch, validation errors by group).
    """
    torch.manual_seed(0)
    freed = _select(module, cfg.fit)
    opt = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=cfg.lr)
    out.mkdir(parents=True, exist_ok=True)

    def validate() -> tuple[float, dict[str, dict[str, float]]]:
        loss, uvs, _ = track_set(module, val, cfg.batch, huber=cfg.huber, tipm=tipm)
        return loss, errors_by_group(val, uvs, cfg.lost_px)

    t0 = time.time()
    v_loss, v_groups = validate()
    best_epoch, best_loss = 0, v_loss
    best_state = {k: v.detach().clone() for k, v in module.state_dict().items()}
    history: list[dict[str, Any]] = [{"epoch": 0, "loss": None, "val_loss": v_loss, "val": v_groups,
                "params": readable(module), "seconds": round(time.time() - t0, 1)}]
    say(f"epoch 0 (start): val loss {v_loss:.4f}  ({time.time() - t0:.0f} s)")
    rng = np.random.default_rng(0)
    interrupted: int | None = None  # the epoch under way when Ctrl-C came
    try:
        for epoch in range(1, cfg.epochs + 1):
            t1 = time.time()
            order = [train[i] for i in rng.permutation(len(train))]
            loss, _, _ = track_set(module, order, cfg.batch, cfg.chunk, cfg.huber, opt,
                                   cfg.clip, tipm=tipm)
            v_loss, v_groups = validate()
            if not math.isfinite(v_loss):
                raise FitError(f"epoch {epoch}: the validation loss is not finite: the fit "
                               "diverged (lower lr)")
            history.append({"epoch": epoch, "loss": loss, "val_loss": v_loss, "val": v_groups,
                            "params": readable(module), "seconds": round(time.time() - t1, 1)})
            mark = ""
            if v_loss < best_loss:
                best_epoch, best_loss = epoch, v_loss
                best_state = {k: v.detach().clone() for k, v in module.state_dict().items()}
                mark = "  (best)"
            say(f"epoch {epoch}: train loss {loss:.4f}, val loss {v_loss:.4f}{mark}  "
                f"({time.time() - t1:.0f} s)")
            (out / "metrics.json").write_text(json.dumps(
                {"history": history, "best_epoch": best_epoch, "freed": freed}, indent=1))
    except KeyboardInterrupt:
        # the epochs done are not lost: the best of them is written as a finished fit's is,
        # said to be from an interrupted fit, and the interrupt goes on to the command
        interrupted = len(history)
    with torch.no_grad():
        module.load_state_dict(best_state)
    kept = history[best_epoch]
    metrics = {"history": history, "best_epoch": best_epoch, "freed": freed,
               "config": dataclasses.asdict(cfg), "val": kept["val"],
               "params": kept["params"]}
    if interrupted is not None:
        metrics["interrupted_in_epoch"] = interrupted
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    plot_history(history, best_epoch, out / "loss_curve.png")
    path = out / "live_tracker.safetensors"
    save_fitted(module, path,
                {**info, "best_epoch": best_epoch, "val_loss": best_loss,
                 "params": kept["params"], "added_by_hand": [],
                 **({"interrupted_in_epoch": interrupted} if interrupted is not None else {})})
    if interrupted is not None:
        say(f"interrupted in epoch {interrupted} of {cfg.epochs}: kept epoch {best_epoch} of "
            f"the {interrupted - 1} done (0: the start); model {path} (not installed)")
        raise KeyboardInterrupt
    return metrics


def plot_history(history: Sequence[dict[str, Any]], best: int, path: Path) -> None:
    """Train and validation loss per epoch, the kept epoch marked (``loss_curve.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.6, 3.0), dpi=100)
    tr = [(h["epoch"], h["loss"]) for h in history if h.get("loss") is not None]
    if tr:
        ax.plot(*zip(*tr, strict=True), "o-", label="train (over the epoch)")
    vv = [(h["epoch"], h["val_loss"]) for h in history]
    ax.plot(*zip(*vv, strict=True), "s-", label="validation")
    ax.plot([best], [history[best]["val_loss"]], "k*", ms=12, label=f"kept (epoch {best})")
    ax.set_yscale("log")
    ax.set_xlabel("epoch (0: the starting point)")
    ax.set_ylabel("Huber loss per coordinate (px)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
