"""Fitting EAKF-STC by gradient descent: batched tracking with truncated BPTT, one or many
processes (``torch.distributed`` + DistributedDataParallel, gloo on CPU).

One optimisation step = one chunk of ``k`` frames of B sequences:

1. every sequence starts at its label on frame 0 (:meth:`EAKFSTC.init_state`, no gradient);
2. :class:`ChunkLoss` (the module DDP wraps) cuts the state from the graph
   (:meth:`EAKFSTC.detach`, which also rebuilds the parameter-derived matrices, so every
   parameter enters the graph inside ``forward``), steps the tracker ``k`` frames and returns
   the Huber loss between the filtered points and the labels (masked where unlabelled);
3. backward (DDP all-reduces the gradients), clip, optimiser step; the state carries on into
   the next chunk with the new parameters.

Loss normalisation: each process's loss is its Huber sum divided by (labelled coordinates in the
*global* chunk) / world size, so DDP's gradient average equals the gradient of the global mean:
2 processes give the parameters of 1 process on the same batch (up to summation order).
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import logging
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import Tensor, nn
from tqdm import tqdm

from torchseam.core.dataset import Dataset
from torchseam.core.report import error_stats
from torchseam.fit.config import PARAM_GROUPS, FitConfig
from torchseam.fit.data import SequenceSet, sequence_group
from torchseam.fit.model_io import FitError
from torchseam.track.fusion import EAKFSTC, FusionState, TrackerConfig
from torchseam.vision.tipm import red_response

__all__ = ["ChunkLoss", "DistInfo", "EpochRecord", "evaluate", "evaluate_folders",
           "init_distributed", "make_module", "select_parameters", "train"]

log = logging.getLogger("torchseam.fit")


# --------------------------------------------------------------------------- distributed

@dataclass(frozen=True)
class DistInfo:
    """This process's place in a torchrun job (rank 0 of 1 without torchrun)."""

    rank: int = 0
    world: int = 1
    local_world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1


def init_distributed() -> DistInfo:
    """Join the torchrun job described by the environment (``WORLD_SIZE``, ``RANK``...) with the
    gloo backend; a plain ``python`` run is rank 0 of 1."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    if not dist.is_initialized():
        dist.init_process_group("gloo")
    return DistInfo(rank=dist.get_rank(), world=dist.get_world_size(),
                    local_world=int(os.environ.get("LOCAL_WORLD_SIZE", str(world))))


def _ddp(module: nn.Module) -> nn.Module:
    """DDP without per-forward buffer syncs (the buffers, dt and p0, never change)."""
    ddp = nn.parallel.DistributedDataParallel
    if "forward_sync_buffers" in inspect.signature(ddp.__init__).parameters:  # torch >= 2.13
        return ddp(module, forward_sync_buffers=False)
    return ddp(module, broadcast_buffers=False)


def _all_sum(x: float, info: DistInfo) -> float:
    if not info.active:
        return x
    t = torch.tensor([x], dtype=torch.float64)
    dist.all_reduce(t)
    return float(t[0])


def barrier(info: DistInfo) -> None:
    """Wait for every process of a distributed fit (nothing when the fit runs alone)."""
    if info.active:
        dist.barrier()


# --------------------------------------------------------------------------- the module

def make_module(tracker: TrackerConfig | Mapping[str, Any] | None = None,
                dtype: str | torch.dtype = torch.float32) -> EAKFSTC:
    """A learnable EAKF-STC in ``dtype`` (its starting point: the config's defaults)."""
    cfg = tracker if isinstance(tracker, TrackerConfig) else TrackerConfig.from_dict(tracker)
    cfg = dataclasses.replace(cfg, learnable=True)
    dt = getattr(torch, dtype) if isinstance(dtype, str) else dtype
    return EAKFSTC(cfg).to(dt)


def select_parameters(module: EAKFSTC, groups: Sequence[str]) -> list[str]:
    """Free the parameters of ``groups`` (:data:`PARAM_GROUPS`), freeze the rest.

    Returns:
        The names of the freed parameters.
    """
    params = dict(module.named_parameters())
    names: set[str] = set()
    for g in groups:
        for pat in PARAM_GROUPS[g]:
            hit = {n for n in params if n.startswith(pat)} if pat.endswith(".") else (
                {pat} & set(params))
            if not hit:
                raise FitError(f"the tracker has no learnable parameter {pat!r} (group {g!r}; "
                               "build it with learnable=True)")
            names |= hit
    for n, p in params.items():
        p.requires_grad_(n in names)
    return sorted(names)


class ChunkLoss(nn.Module):
    """One truncated-BPTT chunk as a module (what DDP wraps).

    ``forward(state, frames, labels, norm)``:
        state: :class:`FusionState` after the frame before the chunk (cut from the graph here).
        frames: (B, k, S, S) grey frames (uint8).
        labels: (B, k, 2) true points, NaN where unlabelled.
        norm: the loss is ``sum Huber / norm`` (see the module docstring).

    Returns ``(loss, new state, uv (B, k, 2) detached)``.
    """

    def __init__(self, tracker: EAKFSTC, huber: float = 2.0) -> None:
        super().__init__()
        self.tracker = tracker
        self.huber = float(huber)

    def forward(self, state: FusionState, frames: Tensor, labels: Tensor, norm: float
                ) -> tuple[Tensor, FusionState, Tensor]:
        state = self.tracker.detach(state)
        uvs = []
        for t in range(frames.shape[1]):
            state, uv, _, _ = self.tracker.step_state(state, frames[:, t])
            uvs.append(uv)
        uv = torch.stack(uvs, dim=1)
        mask = torch.isfinite(labels)
        lab = torch.where(mask, labels, torch.zeros_like(labels))
        pred = torch.where(mask, uv, lab)  # masked entries: zero error, zero gradient
        loss = F.huber_loss(pred, lab, reduction="sum", delta=self.huber) / norm
        return loss, state, uv.detach()


# --------------------------------------------------------------------------- evaluation

def _huber_sum(err: np.ndarray, delta: float) -> float:
    a = np.abs(err)
    return float(np.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta)).sum())


@torch.no_grad()  # not inference_mode: its tensors must not leak into later training
def evaluate(module: EAKFSTC, seqs: SequenceSet, batch: int = 16, lost_px: float = 15.0,
             huber: float = 2.0) -> dict[str, Any]:
    """Track the crops of ``seqs`` from their frame-0 labels; errors on the labelled frames
    after frame 0.

    Returns:
        ``{"loss": mean Huber per labelled coordinate, "groups": {group: error_stats}}``
        (``error_stats``: rmse, max, pct_gt5, pct_lost with lost = error > ``lost_px``).
    """
    dtype = module.eakf.dt.dtype
    errs: dict[str, list[np.ndarray]] = {}
    hsum, hn = 0.0, 0
    for i in range(0, len(seqs), batch):
        idx = list(range(i, min(i + batch, len(seqs))))
        fr, lab = seqs.batch(idx)
        res = module.run_sequence(torch.from_numpy(fr),
                                  torch.from_numpy(lab[:, 0]).to(dtype))
        uv = res.uv.to(torch.float64).numpy()
        for j, s in enumerate(idx):
            n = len(seqs.frames[s])
            d = uv[j, 1:n] - lab[j, 1:n]
            ok = np.isfinite(lab[j, 1:n, 0])
            e = np.linalg.norm(d[ok], axis=1)
            e[~np.isfinite(e)] = np.nan  # a diverged filter counts as lost
            errs.setdefault(seqs.groups[s], []).append(e)
            dd = d[ok]
            dd[~np.isfinite(dd)] = 1e6
            hsum += _huber_sum(dd, huber)
            hn += dd.size
    groups = {g: error_stats(np.concatenate(v), lost_px) for g, v in errs.items()}
    return {"loss": hsum / max(hn, 1), "groups": groups}


def _labels(ds: Dataset) -> np.ndarray:
    """The labels of a folder opened with ``require_labels`` (evaluation)."""
    if ds.labels is None:
        raise FitError(f"{ds.root}: no labels.csv: cannot evaluate on unlabelled frames")
    return ds.labels


@torch.no_grad()
def evaluate_folders(models: Mapping[str, EAKFSTC], dirs: Sequence[str | os.PathLike[str]],
                     batch: int = 8, lost_px: float = 15.0, progress: bool = True
                     ) -> list[dict[str, Any]]:
    """Track whole labelled folders on *full* frames (what the live tracker sees), with every
    model in ``models`` on the same frames, B sequences at a time; each sequence starts at its
    first labelled frame. Frames are read as they are needed (no crops, little memory).

    Returns:
        rows ``{"group", "model", **error_stats}`` per (noise group, model), errors over the
        labelled frames after the start.
    """
    dsets = [Dataset.open(d, require_labels=True) for d in dirs]
    errs: dict[tuple[str, str], list[np.ndarray]] = {}
    order: list[str] = []
    by_size: dict[tuple[int, ...], list[int]] = {}
    for i, ds in enumerate(dsets):
        by_size.setdefault(ds.read(0).shape, []).append(i)
        g = sequence_group(ds.meta)
        if g not in order:
            order.append(g)
    total = sum(len(ds) for ds in dsets)
    bar = tqdm(total=total, desc="evaluate", unit="frame", disable=not progress, leave=False)
    for members in by_size.values():
        for b0 in range(0, len(members), batch):
            idx = members[b0:b0 + batch]
            firsts = [int(np.argmax(dsets[i].labelled)) for i in idx]
            lengths = [len(dsets[i]) - f for i, f in zip(idx, firsts, strict=True)]
            T = max(lengths)

            def frames_at(j: int, idx=idx, firsts=firsts, lengths=lengths) -> Tensor:
                imgs = [red_response(dsets[i].read(f + min(j, n - 1)))
                        for i, f, n in zip(idx, firsts, lengths, strict=True)]
                return torch.from_numpy(np.stack(imgs))

            f0 = frames_at(0)
            uv0 = np.stack([_labels(dsets[i])[f] for i, f in zip(idx, firsts, strict=True)])
            states = {}
            out = {}
            for name, m in models.items():
                dt = m.eakf.dt.dtype
                states[name] = m.init_state(f0, torch.from_numpy(uv0).to(dt))
                out[name] = [torch.from_numpy(uv0)]
            for j in range(1, T):
                fj = frames_at(j)
                for name, m in models.items():
                    states[name], uv, _, _ = m.step_state(states[name], fj)
                    out[name].append(uv.to(torch.float64))
                bar.update(len(idx))
            for name in models:
                uv_all = torch.stack(out[name], dim=1).numpy()
                for j, (i, f, n) in enumerate(zip(idx, firsts, lengths, strict=True)):
                    lab = _labels(dsets[i])[f:f + n]
                    ok = np.isfinite(lab[:, 0])
                    ok[0] = False
                    e = np.linalg.norm(uv_all[j, :n][ok] - lab[ok], axis=1)
                    e[~np.isfinite(e)] = np.nan
                    errs.setdefault((sequence_group(dsets[i].meta), name), []).append(e)
    bar.close()
    rows = []
    for g in order:
        for name in models:
            if (g, name) in errs:
                st = error_stats(np.concatenate(errs[(g, name)]), lost_px)
                rows.append({"group": g, "model": name, **st})
    return rows


# --------------------------------------------------------------------------- training

@dataclass
class EpochRecord:
    """What one epoch did (JSON-able through ``dataclasses.asdict``)."""

    epoch: int
    loss: float | None          # mean Huber per labelled coordinate over the epoch's chunks
    #                             (None for epoch 0: the starting point, validated only)
    steps: int
    seconds: float              # wall time of the training part (no validation)
    sequences: int
    frames: int
    val_loss: float | None = None
    val: dict[str, dict[str, float]] | None = None
    params: dict[str, list[float]] | None = None


def readable_params(module: EAKFSTC) -> dict[str, list[float]]:
    """The tracker's parameters in their natural units (``log_x`` -> x, ``logit_x`` and
    ``x_raw`` -> their squashed values), for logs and the README."""
    out: dict[str, list[float]] = {}
    e = module.eakf
    named = {"eakf.lam_raw": ("lam", e.lam), "eakf.a_raw": ("a", e.a), "eakf.b_raw": ("b", e.b),
             "eakf.log_q": ("Q", e.Q), "eakf.log_r": ("R", e.R)}
    for n, p in module.named_parameters():
        if n in named:
            key, val = named[n]
        else:
            leaf = n.rpartition(".")[2]
            if leaf.startswith("log_"):
                key, val = leaf[4:], p.exp()
            elif leaf.startswith("logit_"):
                key, val = leaf[6:], torch.sigmoid(p)
            else:
                key, val = leaf, p
            if key in out:  # the same leaf name in two sub-modules
                key = n
        out[key] = [round(float(x), 6) for x in val.detach().reshape(-1)]
    return out


def _drop_inference_caches() -> None:
    """Workaround: ``torchseam.track.eakf`` caches small constant tensors on first use; made
    under ``torch.inference_mode`` (any earlier tracking in this process) they cannot enter an
    autograd graph. Empty that cache so training rebuilds them (harmless when absent)."""
    from torchseam.track import eakf

    cache = getattr(eakf, "_ADJ", None)
    if isinstance(cache, dict):
        cache.clear()


def _checkpoint_path(out: Path) -> Path:
    return out / "last.pt"


def _save_checkpoint(path: Path, module: EAKFSTC, opt: torch.optim.Optimizer, epoch: int,
                     history: list[EpochRecord], best: dict[str, Any], cfg: FitConfig) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"epoch": epoch,
             "model": {k: v.detach().clone() for k, v in module.state_dict().items()},
             "optimizer": opt.state_dict(),
             "history": json.dumps([dataclasses.asdict(h) for h in history]),
             "best": {"epoch": best["epoch"], "val_loss": best["val_loss"],
                      "model": best["model"]},
             "config": json.dumps(cfg.to_dict())}
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    torch.save(state, tmp)
    os.replace(tmp, path)


def _load_checkpoint(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise FitError(f"{path}: no checkpoint to resume from (train without --resume first)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise FitError(f"{path}: not a readable checkpoint ({e})") from None


def train(cfg: FitConfig, train_set: SequenceSet, val_set: SequenceSet | None = None, *,
          resume: bool | str | os.PathLike[str] = False, info: DistInfo | None = None,
          log_fn: Callable[[str], None] | None = None) -> tuple[EAKFSTC, list[EpochRecord]]:
    """Fit the EAKF-STC parameters named in ``cfg.fit`` on ``train_set``.

    Args:
        cfg: options (epochs, batch, chunk, lr, huber, clip, seed, dtype, out, tracker...).
        train_set: training crops (every process holds the whole set and takes its shard of
            each batch: sequences ``batch[rank::world]``).
        val_set: held-out crops, validated on rank 0 every ``cfg.val_every`` epochs.
        resume: True: continue from ``cfg.out/last.pt``; a path: from that checkpoint.
        info: the torchrun job (default: :func:`init_distributed`'s answer, single process).
        log_fn: where progress lines go (default ``tqdm.write`` on rank 0).

    Returns:
        The module holding the best parameters (lowest validation loss; the last epoch's
        without a validation set) and the per-epoch history. Rank 0 writes a checkpoint
        (``cfg.out/last.pt``) after every epoch.
    """
    info = info or DistInfo()
    say = log_fn or (tqdm.write if info.main else (lambda s: None))
    _drop_inference_caches()
    torch.manual_seed(cfg.seed)
    module = make_module(cfg.tracker_config(), cfg.dtype)
    dtype = module.eakf.dt.dtype
    freed = select_parameters(module, cfg.fit)
    params = [p for p in module.parameters() if p.requires_grad]
    chunk_mod = ChunkLoss(module, cfg.huber)
    model: nn.Module = chunk_mod
    if info.active:
        model = _ddp(chunk_mod)
    opt = torch.optim.Adam(params, lr=cfg.lr)
    out = Path(cfg.out)
    history: list[EpochRecord] = []
    best: dict[str, Any] = {"epoch": -1, "val_loss": math.inf, "model": {}}
    start = 0
    if resume:
        path = _checkpoint_path(out) if resume is True else Path(resume)
        history, best, start = _resume(path, cfg, module, opt, say)
    N = _check_shards(len(train_set), info)
    if val_set is None and start == 0:
        say("no validation sequences: the last epoch's parameters are kept")
    if val_set is not None and start == 0:  # the starting point's score
        rec, best0 = _starting_point(module, val_set, cfg, info)
        history.append(rec)
        if best0 is not None:
            best = best0
            say(_epoch_line(rec))
    barrier(info)

    for epoch in range(start, cfg.epochs):
        batches = _epoch_batches(cfg, N, info, epoch, say if epoch == start else None)
        n_steps = sum(math.ceil((int(train_set.lengths[b].max()) - 1) / cfg.chunk)
                      for b in batches)
        bar = tqdm(total=n_steps, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="step",
                   disable=not (cfg.progress and info.main), leave=False)
        t0 = time.perf_counter()
        loss_sum, loss_n, steps, frames_seen = 0.0, 0.0, 0, 0
        module.train()
        for b in batches:
            mine = b[info.rank::info.world]
            T = int(train_set.lengths[b].max())
            fr, lab = train_set.batch(mine, T)
            frames = torch.from_numpy(fr)
            labels = torch.from_numpy(lab).to(dtype)
            with torch.no_grad():
                state = module.init_state(frames[:, 0], labels[:, 0])
            for a in range(1, T, cfg.chunk):
                e = min(a + cfg.chunk, T)
                lab_c = labels[:, a:e]
                n_local = float(torch.isfinite(lab_c).sum())
                n_glob = _all_sum(n_local, info)
                if n_glob == 0:
                    with torch.no_grad():
                        _, state, _ = chunk_mod(state, frames[:, a:e], lab_c, 1.0)
                    continue
                loss, state, _ = model(state, frames[:, a:e], lab_c, n_glob / info.world)
                opt.zero_grad(set_to_none=False)
                loss.backward()
                if steps == 0 and epoch == start:
                    _warn_no_gradient(module, say)
                gl = _all_sum(float(loss.detach()), info) / info.world
                if _optimizer_step(opt, params, gl, cfg.clip):
                    loss_sum += gl * n_glob
                    loss_n += n_glob
                else:
                    say(f"epoch {epoch + 1}: non-finite loss or gradient, step skipped")
                steps += 1
                frames_seen += (e - a) * len(b)
                bar.update(1)
                bar.set_postfix(loss=f"{loss_sum / max(loss_n, 1):.3f}")
        bar.close()
        rec = EpochRecord(epoch=epoch + 1, loss=loss_sum / max(loss_n, 1.0), steps=steps,
                          seconds=time.perf_counter() - t0, sequences=sum(len(b) for b in batches),
                          frames=frames_seen, params=readable_params(module))
        if info.main:
            if val_set is not None and ((epoch + 1) % cfg.val_every == 0
                                        or epoch + 1 == cfg.epochs):
                best = _validate(module, val_set, cfg, rec, best)
            history.append(rec)
            say(_epoch_line(rec))
            _save_checkpoint(_checkpoint_path(out), module, opt, epoch, history, best, cfg)
        else:
            history.append(rec)
        barrier(info)
    _keep_best(module, best, say)
    if info.main:
        say("fitted: " + ", ".join(freed))
    return module, history


def _resume(path: Path, cfg: FitConfig, module: EAKFSTC, opt: torch.optim.Optimizer,
            say: Callable[[str], None]) -> tuple[list[EpochRecord], dict[str, Any], int]:
    """Load the checkpoint ``path`` into ``module`` and ``opt``: (history, best, next epoch)."""
    ck = _load_checkpoint(path)
    old = json.loads(ck["config"])
    if sorted(old.get("fit", [])) != sorted(cfg.fit):
        raise FitError(f"{path}: fitted {old.get('fit')}, this run fits {list(cfg.fit)}: "
                       "resume with the same --fit")
    changed = [k for k in ("batch", "chunk", "lr", "huber", "seed", "tracker", "dtype")
               if old.get(k) != cfg.to_dict().get(k)]
    if changed:
        say(f"resume: {', '.join(changed)} changed since {path} (the run will differ "
            "from an uninterrupted one)")
    with torch.no_grad():
        module.load_state_dict(ck["model"])
    opt.load_state_dict(ck["optimizer"])
    history = [EpochRecord(**h) for h in json.loads(ck["history"])]
    start = int(ck["epoch"]) + 1
    say(f"resumed from {path} after epoch {start}")
    return history, dict(ck["best"]), start


def _starting_point(module: EAKFSTC, val_set: SequenceSet, cfg: FitConfig, info: DistInfo
                    ) -> tuple[EpochRecord, dict[str, Any] | None]:
    """Epoch 0's record: the starting parameters' validation score on rank 0 (and the best
    so far: them), an empty record on the other ranks (and None)."""
    if not info.main:
        return EpochRecord(epoch=0, loss=None, steps=0, seconds=0.0, sequences=0, frames=0), None
    module.eval()
    ev = evaluate(module, val_set, cfg.batch, cfg.lost_px, cfg.huber)
    rec = EpochRecord(epoch=0, loss=None, steps=0, seconds=0.0, sequences=0, frames=0,
                      val_loss=ev["loss"], val=ev["groups"], params=readable_params(module))
    best = {"epoch": 0, "val_loss": ev["loss"],
            "model": {k: v.detach().clone() for k, v in module.state_dict().items()}}
    return rec, best


def _check_shards(n: int, info: DistInfo) -> int:
    """``n`` training sequences, at least one per process."""
    if n < info.world:
        raise FitError(f"{n} training sequences for {info.world} processes: each process "
                       "needs at least one")
    return n


def _keep_best(module: EAKFSTC, best: dict[str, Any], say: Callable[[str], None]) -> None:
    """Load the best validated parameters into ``module`` (none validated: leave it)."""
    if not best["model"]:
        return
    with torch.no_grad():
        module.load_state_dict(best["model"])
    which = "the starting point's" if best["epoch"] == 0 else f"epoch {best['epoch']}'s"
    say(f"best validation loss {best['val_loss']:.4f}: keeping {which} parameters")


def _warn_no_gradient(module: EAKFSTC, say: Callable[[str], None]) -> None:
    """After the first backward pass: name the fitted parameters no gradient reached."""
    dead = [n for n, p in module.named_parameters() if p.requires_grad and p.grad is None]
    if dead:
        say(f"warning: no gradient reaches {', '.join(dead)} (they stay put)")


def _optimizer_step(opt: torch.optim.Optimizer, params: list[nn.Parameter], loss: float,
                    clip: float) -> bool:
    """One step (gradients clipped to norm ``clip`` when > 0) unless the loss or a gradient is
    not finite; whether it stepped."""
    finite = all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in params)
    if not (finite and math.isfinite(loss)):
        return False
    if clip > 0:
        torch.nn.utils.clip_grad_norm_(params, clip)
    opt.step()
    return True


def _validate(module: EAKFSTC, val_set: SequenceSet, cfg: FitConfig, rec: EpochRecord,
              best: dict[str, Any]) -> dict[str, Any]:
    """Score ``rec``'s epoch on the validation set (into ``rec``); the best so far."""
    module.eval()
    ev = evaluate(module, val_set, cfg.batch, cfg.lost_px, cfg.huber)
    rec.val_loss, rec.val = ev["loss"], ev["groups"]
    if ev["loss"] < best["val_loss"]:
        return {"epoch": rec.epoch, "val_loss": ev["loss"],
                "model": {k: v.detach().clone() for k, v in module.state_dict().items()}}
    return best


def _epoch_batches(cfg: FitConfig, n: int, info: DistInfo, epoch: int,
                   say: Callable[[str], None] | None) -> list[list[int]]:
    """The epoch's batches of sequence indices (shuffled by seed and epoch); a last batch
    too small to give every process a sequence is dropped (``say`` tells, when given)."""
    g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch)
    perm = torch.randperm(n, generator=g).tolist()
    batches = [perm[i:i + cfg.batch] for i in range(0, n, cfg.batch)]
    if len(batches[-1]) < info.world:  # a process would get no sequence
        if say is not None:
            say(f"{len(batches[-1])} sequences left over in the last batch of each epoch "
                f"for {info.world} processes: dropped (choose N and --batch as multiples "
                f"of {info.world})")
        batches = batches[:-1]
    return batches


def _epoch_line(r: EpochRecord) -> str:
    if r.loss is None:
        s = "epoch 0 (starting point)"
    else:
        s = (f"epoch {r.epoch}: train loss {r.loss:.4f} ({r.steps} steps, {r.seconds:.1f} s, "
             f"{r.frames / max(r.seconds, 1e-9):.0f} frames/s)")
    if r.val is not None:
        s += f"; val loss {r.val_loss:.4f}: " + "; ".join(
            f"{g} rmse {v['rmse']:.2f} max {v['max']:.1f} lost {v['pct_lost']:.1f}%"
            for g, v in r.val.items())
    return s
