"""EAKF-STC: STC supplies the measurement, the EAKF the prediction (METHOD.md section 4).

Per frame k (B sequences at once, no loop over the batch):

1. crop the context window at the filter's prediction for frame k (``Phi X(k-1|k-2)``, so the
   window follows the motion instead of lagging one frame behind it; clamped into the frame);
2. STC detection (eq. 10-11): measurement ``z`` (sub-pixel peak) and peak quality (PSR,
   second-peak ratio);
3. the EAKF's innovation of the delayed update (eq. 21-25) and its normalised squared distance
   ``d2`` (position rows, chi-square with 2 dof under the model);
4. the drift guard (:class:`DriftGuard`) turns quality and ``d2`` into a trust in (0, 1);
5. EAKF update with R scaled by ``r_scale`` (below), then prediction: the output
   position at frame k. The measurement kept for the next equivalent observation
   ``Z(k+1) - Psi Z(k)`` is blended toward its prediction by ``1 - trust`` (``keep`` of
   :func:`~torchseam.track.eakf.eakf_update`), so a rejected outlier does not leak into the
   next update through Psi nor widen the next gate;
6. STC learns at the *filtered* estimate (the context is re-centred on it) with learning rate
   ``rho * sigmoid(k_l (trust - t_l))``, so a distrusted frame (glare, spatter, a vanished
   stripe) does not enter the context model: STC's h_sc of a structureless (noise) window is
   huge (``FFT(c) / FFT(prior)`` with a small ``FFT(prior)``), so even a few percent of it
   would swamp H_stc, hence a sharp, not proportional, switch;
7. status: ``TRACKED`` when trust >= 0.5, ``COASTING`` when not, ``LOST`` after more than
   ``max_coast`` coasting frames in a row or when the position std exceeds ``lost_std``
   (a trusted frame brings it back to ``TRACKED``).

Drift guard (smooth, every threshold and slope a learnable tensor)::

    trust = sigmoid(k_psr (log psr - log psr0)) * sigmoid(k_2 (second0 - second_ratio))
            * sigmoid(k_g (gate - sqrt(d2)) - k_s log(spread / spread0))
    r_scale = s_max ** sigmoid(k_r (t_r - trust))   # ~1 when trusted, ~s_max when not
    rho_scale = sigmoid(k_l (trust - t_l))   # learning only on clearly trusted frames

It is a soft AND of three tests: the peak must stand out of its sidelobe (sharpness), no other
peak may compete with it (the multi-peak failure of METHOD.md section 2), and it must lie inside
the filter's innovation gate. ``spread = det(S_pos)^(1/4)`` is the gate's size in px: as in
probabilistic data association, the likelihood ratio of "target here" against "clutter anywhere
in the window" is ``A / (2 pi sqrt(det S)) exp(-d2 / 2)``, so a wide gate (after coasting, when
P has grown) is worth less (k_s = 2 is that ratio's own exponent). Without this term the gate
accepts anything once P has grown, which is exactly when clutter is most likely to be taken.
The R inflation is a sigmoid of trust in log space (a measurement at trust 0.3 must not pull
a filter whose P has grown while coasting), so gradients stay useful across decades of R, and
it enters the EAKF through its exact coloured-noise bookkeeping
(:mod:`torchseam.track.eakf`). Everything is differentiable almost everywhere (argmax and the
local-maximum test select, the values carry gradients).

Defaults live in :class:`TrackerConfig` (one dataclass; ``TrackerConfig.from_dict`` loads a
mapping such as a YAML section).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.fft
import torch
from torch import Tensor, nn

from torchseam.core.checks import (
    InputError,
    as_float,
    check_batch,
    check_device,
    check_shape,
)
from torchseam.core.kernels import load_kernels
from torchseam.track.base import Tracker, TrackStatus
from torchseam.track.config import TrackerConfig
from torchseam.track.eakf import EAKF, EAKFMatrices, EAKFState
from torchseam.track.stc import STC, STCState, cached, confidence_map, weight_window
from torchseam.vision.tipm import red_response

_D = TrackerConfig()  # the defaults

__all__ = ["DriftGuard", "EAKFSTC", "FusionState", "LiteEAKFSTC", "LiteTracker", "SequenceResult",
           "StepTimer", "TrackStatus", "TrackerConfig"]


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


class DriftGuard(nn.Module):
    """Smooth trust of a measurement from peak quality and innovation (see module docstring).

    Parameters (0-dim tensors, raw forms keep them in range): ``log_psr0``, ``log_psr_slope``,
    ``logit_second0``, ``log_second_slope``, ``log_gate``, ``log_gate_slope``,
    ``log_spread0``, ``log_spread_slope``, ``log_r_scale_max``, ``logit_r_trust``,
    ``log_r_slope``, ``logit_learn_trust``, ``log_learn_slope``.

    Example:
        >>> g = DriftGuard()
        >>> trust, r_scale, rho_scale = g(torch.tensor([20.0, 3.0]), torch.tensor([0.2, 0.9]),
        ...                               torch.tensor([1.0, 30.0]), torch.tensor([0.8, 0.8]))
        >>> (trust > 0.5).tolist(), bool(r_scale[1] > 100.0)
        ([True, False], True)
    """

    # registered as parameters or buffers in __init__
    log_psr0: Tensor
    log_psr_slope: Tensor
    logit_second0: Tensor
    log_second_slope: Tensor
    log_gate: Tensor
    log_gate_slope: Tensor
    log_spread0: Tensor
    log_spread_slope: Tensor
    log_r_scale_max: Tensor
    logit_r_trust: Tensor
    log_r_slope: Tensor
    logit_learn_trust: Tensor
    log_learn_slope: Tensor

    def __init__(self, psr0: float = _D.psr0, psr_slope: float = _D.psr_slope,
                 second0: float = _D.second0, second_slope: float = _D.second_slope,
                 gate: float = _D.gate, gate_slope: float = _D.gate_slope,
                 spread0: float = _D.spread0, spread_slope: float = _D.spread_slope,
                 r_scale_max: float = _D.r_scale_max, r_trust: float = _D.r_trust,
                 r_slope: float = _D.r_slope, learn_trust: float = _D.learn_trust,
                 learn_slope: float = _D.learn_slope,
                 learnable: bool = _D.learnable) -> None:
        super().__init__()
        for name, v in (("psr0", psr0), ("psr_slope", psr_slope), ("second_slope", second_slope),
                        ("gate", gate), ("gate_slope", gate_slope), ("spread0", spread0),
                        ("spread_slope", spread_slope), ("r_slope", r_slope),
                        ("learn_slope", learn_slope)):
            if not v > 0:
                raise InputError(f"{name}: expected > 0, got {v}")
        for name, v in (("second0", second0), ("r_trust", r_trust),
                        ("learn_trust", learn_trust)):
            if not 0.0 < v < 1.0:
                raise InputError(f"{name}: expected in (0, 1), got {v}")
        if not r_scale_max >= 1.0:
            raise InputError(f"r_scale_max: expected >= 1, got {r_scale_max}")
        raw = {"log_psr0": math.log(psr0), "log_psr_slope": math.log(psr_slope),
               "logit_second0": _logit(second0), "log_second_slope": math.log(second_slope),
               "log_gate": math.log(gate), "log_gate_slope": math.log(gate_slope),
               "log_spread0": math.log(spread0), "log_spread_slope": math.log(spread_slope),
               "log_r_scale_max": math.log(max(r_scale_max, 1.0 + 1e-6)),
               "logit_r_trust": _logit(r_trust), "log_r_slope": math.log(r_slope),
               "logit_learn_trust": _logit(learn_trust), "log_learn_slope": math.log(learn_slope)}
        for name, v in raw.items():
            t = torch.tensor(v, dtype=torch.get_default_dtype())
            if learnable:
                self.register_parameter(name, nn.Parameter(t))
            else:
                self.register_buffer(name, t)

    def natural(self) -> dict[str, Tensor]:
        """The parameters in natural units, by :class:`TrackerConfig` field name (for logs)."""
        return {"psr0": self.log_psr0.exp(), "psr_slope": self.log_psr_slope.exp(),
                "second0": torch.sigmoid(self.logit_second0),
                "second_slope": self.log_second_slope.exp(), "gate": self.log_gate.exp(),
                "gate_slope": self.log_gate_slope.exp(), "spread0": self.log_spread0.exp(),
                "spread_slope": self.log_spread_slope.exp(),
                "r_scale_max": self.log_r_scale_max.exp(),
                "r_trust": torch.sigmoid(self.logit_r_trust),
                "r_slope": self.log_r_slope.exp(),
                "learn_trust": torch.sigmoid(self.logit_learn_trust),
                "learn_slope": self.log_learn_slope.exp()}

    def constants(self) -> Tensor:
        """The natural-unit parameters stacked (13,): k_psr, log psr0, k_2, second0, k_g, gate,
        k_s, log spread0, log s_max, k_l, t_l, k_r, t_r. Build once per sequence and pass to
        :meth:`forward`."""
        return torch.stack([
            self.log_psr_slope.exp(), self.log_psr0, self.log_second_slope.exp(),
            torch.sigmoid(self.logit_second0), self.log_gate_slope.exp(), self.log_gate.exp(),
            self.log_spread_slope.exp(), self.log_spread0, self.log_r_scale_max,
            self.log_learn_slope.exp(), torch.sigmoid(self.logit_learn_trust),
            self.log_r_slope.exp(), torch.sigmoid(self.logit_r_trust)])

    def forward(self, psr: Tensor, second_ratio: Tensor, d2: Tensor, spread: Tensor,
                c: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Trust, R scale and rho scale.

        Args:
            psr: (B,) peak-to-sidelobe ratio of the confidence map.
            second_ratio: (B,) second-peak ratio in [0, 1].
            d2: (B,) squared Mahalanobis distance of the innovation.
            spread: (B,) size of the innovation gate in px, ``det(S_pos)^(1/4)`` (the geometric
                mean of the two axes' innovation std).
            c: :meth:`constants` (computed here when None).

        Returns:
            trust (B,) in (0, 1), r_scale (B,) in [1, s_max], rho_scale (B,) in (0, 1).
        """
        c = self.constants() if c is None else c
        tiny = torch.finfo(psr.dtype).tiny
        feats = torch.stack([torch.log(psr.clamp_min(tiny)), second_ratio,
                             torch.sqrt(d2 + 1e-12), torch.log(spread.clamp_min(tiny))])
        # logits of the three tests, (3, B): slope * (value - threshold), signs folded in
        l_psr = c[0] * (feats[0] - c[1])
        l_sec = c[2] * (c[3] - feats[1])
        l_gate = c[4] * (c[5] - feats[2]) - c[6] * (feats[3] - c[7])
        trust = torch.sigmoid(torch.stack([l_psr, l_sec, l_gate])).prod(dim=0)
        r_scale = torch.exp(c[8] * torch.sigmoid(c[11] * (c[12] - trust)))
        rho_scale = torch.sigmoid(c[9] * (trust - c[10]))
        return trust, r_scale, rho_scale


class StepTimer:
    """Per-step wall times at negligible cost: ``perf_counter_ns`` on CPU; on CUDA a pair of
    events per step, read (and synchronised) only when :meth:`ms` is called."""

    def __init__(self, maxlen: int = 100_000) -> None:
        self._cpu: deque[int] = deque(maxlen=maxlen)
        self._cuda: deque[tuple[Any, Any]] = deque(maxlen=maxlen)
        self._t0 = 0
        self._ev: Any = None

    def start(self, device: torch.device) -> None:
        if device.type == "cuda":
            self._ev = torch.cuda.Event(enable_timing=True)
            self._ev.record()
        else:
            self._t0 = time.perf_counter_ns()

    def stop(self, device: torch.device) -> None:
        if device.type == "cuda":
            end = torch.cuda.Event(enable_timing=True)
            end.record()
            self._cuda.append((self._ev, end))
        else:
            self._cpu.append(time.perf_counter_ns() - self._t0)

    def ms(self) -> list[float]:
        """Step times in ms, oldest first (CPU steps then CUDA steps)."""
        out = [t * 1e-6 for t in self._cpu]
        if self._cuda:
            torch.cuda.synchronize()
            out += [a.elapsed_time(b) for a, b in self._cuda]
        return out

    def clear(self) -> None:
        self._cpu.clear()
        self._cuda.clear()


@dataclass
class FusionState:
    """State of B sequences: STC and EAKF states, cached filter matrices, status counters."""

    stc: STCState
    kf: EAKFState
    mats: EAKFMatrices
    guard: Tensor   # (13,) DriftGuard.constants()
    coast: Tensor   # (B,) int64 consecutive coasting frames
    status: Tensor  # (B,) int64 TrackStatus of the newest frame
    frame: int = 0


@dataclass
class SequenceResult:
    """Output of :meth:`EAKFSTC.run_sequence`; every field is (B, T) or (B, T, 2)."""

    uv: Tensor
    status: Tensor
    z: Tensor
    trust: Tensor
    psr: Tensor
    second_ratio: Tensor
    d2: Tensor
    std: Tensor
    extra: dict[str, Tensor] = field(default_factory=dict)


QUALITY_KEYS = ("z", "trust", "psr", "second_ratio", "n_peaks", "peak", "d2", "r_scale",
                "rho_scale", "std")


class EAKFSTC(nn.Module):
    """Batched EAKF-STC seam-feature tracker with a learnable drift guard.

    Args:
        config: a :class:`TrackerConfig` or a mapping of its fields (None: defaults).
        **overrides: fields overriding ``config``.

    Attributes:
        stc: the :class:`~torchseam.track.stc.STC` module.
        eakf: the :class:`~torchseam.track.eakf.EAKF` module.
        guard: the :class:`DriftGuard`.
        timer: :class:`StepTimer` of :meth:`step` calls (read with :meth:`timings_ms`).

    Example:
        >>> trk = EAKFSTC(window=(32, 32), target=(16, 16))
        >>> frames = torch.rand(2, 4, 96, 128)
        >>> with torch.inference_mode():
        ...     trk.init(frames[:, 0], torch.tensor([[64.0, 48.0], [60.0, 40.0]]))
        ...     uv, status, q = trk.step(frames[:, 1])
        >>> tuple(uv.shape), tuple(status.shape), sorted(q)[:3]
        ((2, 2), (2,), ['d2', 'n_peaks', 'peak'])
    """

    def __init__(self, config: TrackerConfig | Mapping[str, Any] | None = None,
                 **overrides: Any) -> None:
        super().__init__()
        if isinstance(config, TrackerConfig):
            cfg = dataclasses.replace(config, **overrides) if overrides else config
        else:
            cfg = TrackerConfig.from_dict(config, **overrides)
        self.config = cfg
        self.stc = STC(cfg.window, cfg.target, alpha=cfg.alpha, beta=cfg.beta, rho=cfg.rho,
                       sigma=cfg.sigma, eps=cfg.eps, scale_update=cfg.scale_update,
                       scale_lambda=cfg.scale_lambda, scale_frames=cfg.scale_frames,
                       peak=cfg.peak, temperature=cfg.temperature, crop=cfg.crop,
                       exclude=cfg.exclude, reg=cfg.reg, anchor=cfg.anchor,
                       anchor_frames=cfg.anchor_frames, learnable=cfg.learnable)
        self.eakf = EAKF(cfg.frame_rate, lam=cfg.lam, a=cfg.a, b=cfg.b, q=cfg.q,
                         r=(cfg.r_pos, cfg.r_disp), p0=cfg.p0, learnable=cfg.learnable)
        self.guard = DriftGuard(cfg.psr0, cfg.psr_slope, cfg.second0, cfg.second_slope,
                                cfg.gate, cfg.gate_slope, cfg.spread0, cfg.spread_slope,
                                cfg.r_scale_max, cfg.r_trust, cfg.r_slope, cfg.learn_trust,
                                cfg.learn_slope,
                                learnable=cfg.learnable)
        if cfg.max_coast < 0 or not cfg.lost_std > 0:
            raise InputError("max_coast must be >= 0 and lost_std > 0")
        self.timer = StepTimer(cfg.timing_window)
        self.state: FusionState | None = None

    # ------------------------------------------------------------------ functional core
    def init_state(self, frames0: Tensor, uv0: Tensor) -> FusionState:
        """Start B sequences at ``uv0`` in ``frames0``.

        Args:
            frames0: (B, Himg, Wimg) first grey frames (full frames or crops; uint8 or float).
            uv0: (B, 2) feature point (u, v) in those frames (e.g. TIPM on the first clean
                frame); must be finite and inside the frame.

        Returns:
            :class:`FusionState` at frame 0 (status TRACKED).
        """
        check_shape(frames0, ("B", "Himg", "Wimg"), "frames0")
        B, hi, wi = frames0.shape
        check_shape(uv0, (B, 2), "uv0")
        check_device(uv0, "uv0", self.eakf.dt)
        uvd = uv0.detach()
        bad = ~torch.isfinite(uvd).all(dim=1) | (uvd[:, 0] < -0.5) | (uvd[:, 0] > wi - 0.5) \
            | (uvd[:, 1] < -0.5) | (uvd[:, 1] > hi - 0.5)
        if bool(bad.any()):
            i = int(bad.nonzero()[0, 0])
            raise InputError(f"uv0: sequence {i} starts at (u, v) = "
                             f"({float(uvd[i, 0]):.1f}, {float(uvd[i, 1]):.1f}), outside "
                             f"the {wi} x {hi} frame")
        uv0 = as_float(uv0, self.eakf.dt)
        stc = self.stc.init_state(frames0, uv0)
        kf = self.eakf.init_state(uv0)
        z = torch.zeros(B, dtype=torch.long, device=uv0.device)
        return FusionState(stc=stc, kf=kf, mats=self.eakf.matrices(),
                           guard=self.guard.constants(), coast=z, status=z.clone(), frame=0)

    def step_state(self, state: FusionState, frames: Tensor
                   ) -> tuple[FusionState, Tensor, Tensor, dict[str, Tensor]]:
        """One EAKF-STC step on the next frames (pure: returns a new state).

        Args:
            state: current state.
            frames: (B, Himg, Wimg) next grey frames.

        Returns:
            (new state, uv (B, 2), status (B,) int64 :class:`TrackStatus`, quality dict of (B,)
            tensors: ``z`` (B, 2) raw STC measurement, ``trust``, ``psr``, ``second_ratio``,
            ``n_peaks``, ``peak``, ``d2``, ``r_scale``, ``rho_scale``, ``std`` (position std,
            px, the larger axis)).
        """
        B = state.coast.shape[0]
        check_shape(frames, ("B", "Himg", "Wimg"), "frames")
        check_batch(frames, "frames", B)
        cfg, m = self.config, state.mats
        hi, wi = frames.shape[-2:]
        pred = state.kf.predict_uv(m.Phi)                              # 1. prediction
        bound = cached(("bound", wi, hi, pred.device, pred.dtype),
                        lambda: pred.new_tensor([wi - 1.0, hi - 1.0]))
        centre = torch.minimum(pred.clamp_min(0.0), bound)
        det = self.stc.detect(state.stc, frames, centre)               # 2. measurement
        inn = self.eakf.innovation(state.kf, det.uv, m=m)              # 3. innovation
        q = det.quality
        spread = (inn.S[..., 0, 0].prod(dim=-1)).clamp_min(0.0) ** 0.25
        trust, r_scale, rho_scale = self.guard(q["psr"], q["second_ratio"], inn.d2_pos,
                                               spread, state.guard)    # 4. drift guard
        kf = self.eakf.update(state.kf, inn, r_scale, m=m, keep=trust)  # 5. filter
        uv = kf.uv
        stc = self.stc.learn(state.stc, frames, uv, rho_scale)         # 6. re-centre, learn
        std = kf.uv_var.detach().amax(dim=1).clamp_min(0.0).sqrt()     # 7. status
        distrusted = (trust.detach() < 0.5).long()  # TRACKED 0 / COASTING 1
        coast = (state.coast + 1) * distrusted
        lost = (coast > cfg.max_coast) | (std > cfg.lost_std)
        status = torch.where(lost, int(TrackStatus.LOST), distrusted)
        quality = {"z": det.uv, "trust": trust, "psr": q["psr"],
                   "second_ratio": q["second_ratio"], "n_peaks": q["n_peaks"], "peak": q["peak"],
                   "d2": inn.d2_pos, "r_scale": r_scale, "rho_scale": rho_scale, "std": std}
        new = FusionState(stc=stc, kf=kf, mats=m, guard=state.guard, coast=coast,
                          status=status, frame=state.frame + 1)
        return new, uv, status, quality

    def detach(self, state: FusionState) -> FusionState:
        """``state`` cut from the autograd graph, with parameter-derived caches rebuilt from the
        current parameters (truncated BPTT; also call after an optimiser step)."""
        return FusionState(stc=self.stc.detach_state(state.stc), kf=state.kf.detach(),
                           mats=self.eakf.matrices(), guard=self.guard.constants(),
                           coast=state.coast, status=state.status, frame=state.frame)

    # ------------------------------------------------------------------ stateful API
    def init(self, frames0: Tensor, uv0: Tensor) -> None:
        """Start tracking (see :meth:`init_state`); the state is kept in ``self.state``."""
        self.state = self.init_state(frames0, uv0)

    def step(self, frames: Tensor) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """Track the next frames (B, Himg, Wimg): returns (uv (B, 2), status (B,), quality)."""
        if self.state is None:
            raise InputError("EAKFSTC.step: call init(frames0, uv0) first")
        dev = self.eakf.dt.device
        self.timer.start(dev)
        self.state, uv, status, q = self.step_state(self.state, frames)
        self.timer.stop(dev)
        return uv, status, q

    def reanchor(self, frames: Tensor, uv: Tensor, rate: float | Tensor = 1.0) -> None:
        """Move the kept state onto an absolute fix ``uv`` of the feature point (TIPM's corner
        in a clean moment) without restarting: the filter's positions (now and the frame
        before) and its kept measurement shift together, so velocity and covariance survive;
        STC re-learns its context at ``uv`` with weight ``rate`` (1: the model is replaced, its
        drift forgotten). A restart (:meth:`init`) would instead throw away the velocity and
        open the gate wide for the next frames, when spatter is most likely to be taken.

        Args:
            frames: (B, Himg, Wimg) the frames the fix was found in (the newest step's).
            uv: (B, 2) the fix.
            rate: STC learning weight in (0, 1].

        Example:
            >>> trk = EAKFSTC(window=(32, 32), target=(16, 16))
            >>> f = torch.rand(1, 96, 128)
            >>> with torch.inference_mode():
            ...     trk.init(f, torch.tensor([[64.0, 48.0]]))
            ...     trk.reanchor(f, torch.tensor([[66.0, 47.0]]))
            >>> trk.state.kf.uv.tolist()
            [[66.0, 47.0]]
        """
        if self.state is None:
            raise InputError("EAKFSTC.reanchor: call init(frames0, uv0) first")
        s = self.state
        B = s.coast.shape[0]
        check_shape(frames, ("B", "Himg", "Wimg"), "frames")
        check_batch(frames, "frames", B)
        check_shape(uv, (B, 2), "uv")
        uv = as_float(uv, s.kf.x)
        if not bool(torch.isfinite(uv).all()):
            raise InputError("reanchor: uv must be finite")
        d = uv - s.kf.uv
        shift = torch.zeros_like(s.kf.x)
        shift[..., 0], shift[..., 2] = d, d   # u(k) and u(k-1): the velocity is kept
        kf = dataclasses.replace(s.kf, x=s.kf.x + shift)
        zshift = torch.zeros_like(s.kf.Z)
        zshift[..., 0] = d                    # the kept position measurement, not its step
        kf.Z = s.kf.Z + zshift
        if s.kf.x_post is not None:
            kf.x_post = s.kf.x_post + shift
        rate_t = torch.as_tensor(rate, dtype=uv.dtype, device=uv.device).expand(B)
        stc = self.stc.learn(s.stc, frames, uv, rate_t / self.stc.rho)
        z = torch.zeros_like(s.coast)
        self.state = dataclasses.replace(s, stc=stc, kf=kf, coast=z, status=z.clone())

    def detach_state(self) -> None:
        """Cut the kept state from the graph (truncated BPTT)."""
        if self.state is not None:
            self.state = self.detach(self.state)

    def timings_ms(self) -> list[float]:
        """Wall time of each :meth:`step` so far, in ms."""
        return self.timer.ms()

    def run_sequence(self, frames: Tensor, uv0: Tensor, detach_every: int | None = None
                     ) -> SequenceResult:
        """Track whole sequences (training and batched evaluation).

        Args:
            frames: (B, T, Himg, Wimg) grey frames (uint8 or float).
            uv0: (B, 2) feature point in frame 0.
            detach_every: cut the autograd graph every this many frames (truncated BPTT);
                None keeps the whole graph (when gradients are enabled).

        Returns:
            :class:`SequenceResult` with uv (B, T, 2) (``uv[:, 0] = uv0``), status (B, T), the raw
            STC measurement z (B, T, 2) and per-frame trust, psr, second_ratio, d2, std (B, T)
            (frame 0: z = uv0, trust 1, d2 0, psr/second_ratio NaN-free placeholders 0).
        """
        check_shape(frames, ("B", "T", "Himg", "Wimg"), "frames")
        if detach_every is not None and detach_every < 1:
            raise InputError(f"detach_every: expected >= 1 or None, got {detach_every}")
        B, T = frames.shape[:2]
        state = self.init_state(frames[:, 0], uv0)
        uv = state.kf.uv
        zeros = uv.new_zeros(B)
        cols: dict[str, list[Tensor]] = {
            "uv": [uv], "z": [uv], "status": [state.status], "trust": [zeros + 1.0],
            "psr": [zeros], "second_ratio": [zeros], "d2": [zeros], "std": [zeros]}
        for t in range(1, T):
            if detach_every and t % detach_every == 0:
                state = self.detach(state)
            state, uv, status, q = self.step_state(state, frames[:, t])
            cols["uv"].append(uv)
            cols["status"].append(status)
            for k in ("z", "trust", "psr", "second_ratio", "d2", "std"):
                cols[k].append(q[k])
        out: dict[str, Any] = {k: torch.stack(v, dim=1) for k, v in cols.items()}
        self.state = state
        return SequenceResult(**out)


# --------------------------------------------------------------------------- the numpy twin
# EAKF-STC for one live stream (B = 1) in numpy: the inference twin of :class:`EAKFSTC`.
#
# The torch module is what is fitted and what evaluates batches; at B = 1 on a CPU its ~800 tiny
# tensor ops per frame cost more in dispatch (~2-3 ms) than in arithmetic. This twin runs the
# same equations, with the same parameters read from a module, as ~120 numpy calls on (64, 64)
# windows and one compiled kernel for the confidence map's peak and its quality
# (:mod:`torchseam.track._kernels`; ~0.35 ms a frame in all), and it crops the red-stripe
# response from the colour frame only where the windows lie instead of converting the whole
# frame. It is inference only: no gradients, no batch, the module's settings for live tracking
# (``crop="nearest"``, ``peak="subpixel"``, no scale update); anything else is refused, not
# approximated.
#
# Equivalence: in float64 it gives the module's points, statuses and quality scores to ~1e-9
# (``tests/test_track_lite.py`` steps both through simulated heavy-arc frames, re-anchoring
# included). The module runs in float32, so the twin's float64 answers differ from it by
# rounding, which can flip a near-tie in the argmax on rare frames; the accuracy figures in
# ``docs/benchmarks.md`` are the twin's.

_TINY = float(np.finfo(np.float64).tiny)


def _pocketfft():
    """pocketfft's transforms, which ``scipy.fft.rfft2`` / ``irfft2`` end in, to call without
    scipy's dispatch (~10 us of the ~20 us of a (64, 64) transform; two or three a frame), or
    None: used only when they give scipy.fft's numbers to the bit on a test array (scipy's
    private module may move)."""
    try:
        from scipy.fft._pocketfft import pypocketfft as pfft
        x = np.random.default_rng(0).normal(size=(8, 6))
        X = scipy.fft.rfft2(x)
        if (np.array_equal(pfft.r2c(x, (0, 1), True, 0, None, 1), X)
                and np.array_equal(pfft.c2r(1j * X + X, (0, 1), 6, False, 2, None, 1),
                                   scipy.fft.irfft2(1j * X + X, s=(8, 6)))):
            return pfft
    except Exception:  # noqa: BLE001 - any trouble: scipy.fft as it is
        pass
    return None


_PFFT = _pocketfft()


def _rfft2(x: np.ndarray) -> np.ndarray:
    """``scipy.fft.rfft2(x)`` of a (H, W) float64 array."""
    if _PFFT is None:
        return scipy.fft.rfft2(x)
    return _PFFT.r2c(np.ascontiguousarray(x, dtype=np.float64), (0, 1), True, 0, None, 1)


def _irfft2(X: np.ndarray, s: tuple[int, int]) -> np.ndarray:
    """``scipy.fft.irfft2(X, s=s)`` of a (H, W // 2 + 1) complex128 array."""
    if _PFFT is None:
        return scipy.fft.irfft2(X, s=s)
    return _PFFT.c2r(np.ascontiguousarray(X, dtype=np.complex128), (0, 1), int(s[1]), False, 2,
                     None, 1)


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


class LiteEAKFSTC:
    """B = 1 numpy EAKF-STC with the parameters of an :class:`EAKFSTC` module.

    Build with :meth:`from_module`. Frames are (H, W) grey or (H, W, 3) BGR uint8 (the grey
    image is then the red-stripe response ``R - max(G, B)``, computed per window). The state
    names follow :mod:`torchseam.track.eakf` and :mod:`torchseam.track.stc` without the
    batch dimension: ``x`` (2, 4), ``P`` (2, 4, 4), ``Z`` (2, 2), ``s`` (2, 2), ``s_ref`` (2,),
    ``H_f`` (H, W//2+1) complex.

    Example:
        >>> import numpy as np
        >>> trk = LiteEAKFSTC.from_module(EAKFSTC(window=(32, 32), target=(16, 16)))
        >>> f = np.zeros((96, 128), np.uint8); f[48, :] = 200; f[:, 64] = 200
        >>> trk.init(f, np.array([64.0, 48.0]))
        >>> uv, status, q = trk.step(f)
        >>> np.round(uv, 3).tolist(), status
        ([64.0, 48.0], 0)
    """

    def __init__(self, params: dict) -> None:
        self.h, self.w = params["window"]
        self.weight = params["weight"]            # (H, W) focus window w_sigma (eq. 5)
        self.conf_f = params["conf_f"]            # (H, W//2+1) rfft2 of c (eq. 1)
        self.rho, self.eps = params["rho"], params["eps"]
        self.reg = params.get("reg", 0.0)         # > 0: eq. 8 regularised (Wiener)
        self.anchor = params.get("anchor", 0.0)   # weight of the start model in detection
        self.anchor_frames = params.get("anchor_frames", 1)
        self.H_ref: np.ndarray | None = None
        self.exclude = params["exclude"]
        self.Phi, self.GQG = params["Phi"], params["GQG"]          # (2, 4, 4)
        self.H_star, self.R, self.psi = params["H_star"], params["R"], params["psi"]
        self.p0 = params["p0"]                    # (2, 4)
        self.c = params["guard"]                  # (13,) DriftGuard.constants()
        self.max_coast, self.lost_std = params["max_coast"], params["lost_std"]
        h, w = self.h, self.w
        # the fourier_shift phase ramps' angular frequencies (rows, half-spectrum columns)
        self._fy = np.fft.fftfreq(h) * (-2.0 * math.pi)
        self._fx = np.fft.rfftfreq(w) * (-2.0 * math.pi)
        self._ar_h = np.arange(h) - h // 2
        self._ar_w = np.arange(w) - w // 2
        self._e = max(self.exclude, 1)  # the peak's area left out of the sidelobe: +-e
        self._even = not (h % 2 or w % 2)  # competing peaks on 2x2-block maxima (see stc.py)
        self._eb = (self.exclude + 1) // 2 if self._even else self.exclude
        self.H_f: np.ndarray | None = None
        # (the anchored model of (id(H_f), id(H_ref)), and the two arrays: see _model)
        self._anchored: tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray] | None = None
        self.frame = 0
        # (frame id, crop centre) and the prior spectrum of the last window: the learning step
        # re-crops at the filtered point, usually the pixel it detected at. Valid within one
        # step only (frame ids are reused): cleared when a step or re-anchoring ends.
        self._last_prior: tuple[tuple[int, int, int], np.ndarray] | None = None
        # learning steps not applied yet (see idle): (window or None, its prior spectrum or
        # None, centre, rho scale), in order
        self._pending: list[tuple[np.ndarray | None, np.ndarray | None, np.ndarray, float]] = []
        # numba: compiled (or loaded) now, not on the first frame
        kernels = load_kernels(__package__)
        self._peak_quality = kernels.peak_quality
        self._red_window = kernels.red_window
        # the filter's state, set by init (with H_f: None until then)
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.Z: np.ndarray | None = None
        self.s: np.ndarray | None = None
        self.s_ref: np.ndarray | None = None
        self.x_post: np.ndarray | None = None
        self.coast = 0
        self.status = int(TrackStatus.TRACKED)

    @classmethod
    def from_module(cls, module: EAKFSTC) -> LiteEAKFSTC:
        """Read the natural parameters of ``module`` (any dtype or device) once."""
        cfg = module.config
        stc = module.stc
        if stc.crop != "nearest" or stc.peak != "subpixel" or stc.scale_update:
            raise InputError(
                f"LiteEAKFSTC runs crop='nearest', peak='subpixel' without the scale update; "
                f"this module has crop={stc.crop!r}, peak={stc.peak!r}, "
                f"scale_update={stc.scale_update} (use the torch module)")

        def npy(t: Tensor) -> np.ndarray:
            return t.detach().to("cpu").double().numpy()

        import torch  # the module's parameters are tensors; the twin's state is not

        with torch.no_grad():
            m = module.eakf.matrices()
            weight = weight_window(stc.window_size, stc.sigma.detach().double())
            conf = confidence_map(stc.window_size, stc.alpha.detach().double(),
                                  stc.beta.detach().double())
            return cls({
                "window": stc.window_size, "weight": npy(weight),
                "conf_f": np.fft.rfft2(npy(conf)), "rho": float(stc.rho), "eps": stc.eps,
                "exclude": stc.exclude, "reg": float(stc.reg), "anchor": float(stc.anchor),
                "anchor_frames": stc.anchor_frames, "Phi": npy(m.Phi), "GQG": npy(m.GQG),
                "H_star": npy(m.H_star), "R": npy(m.R), "psi": npy(m.psi),
                "p0": npy(module.eakf.p0).reshape(2, 4) * np.ones((2, 1)),
                "guard": npy(module.guard.constants()), "max_coast": cfg.max_coast,
                "lost_std": cfg.lost_std})

    # ------------------------------------------------------------------ windows
    @staticmethod
    def _frame(frame: np.ndarray) -> np.ndarray:
        if not isinstance(frame, np.ndarray) or not (
                frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)):
            raise InputError(
                f"frame: expected an (H, W) grey or (H, W, 3) BGR array, got "
                f"{type(frame).__name__} {getattr(frame, 'shape', '')}")
        return frame

    def _window(self, frame: np.ndarray, c: np.ndarray) -> np.ndarray:
        """(H, W) float64 grey window whose index (H//2, W//2) is pixel c (2,) int (u, v);
        border pixels replicated (``extract_windows`` in ``nearest`` mode)."""
        hi, wi = frame.shape[:2]
        u, v = int(c[0]), int(c[1])
        r0, c0 = v - self.h // 2, u - self.w // 2
        if frame.ndim == 3 and frame.dtype == np.uint8 and frame.flags.c_contiguous:
            # crop (border replicated), red response and float64 in one compiled pass
            win = np.empty((self.h, self.w))
            self._red_window(frame, r0, c0, win)
            return win
        if r0 >= 0 and c0 >= 0 and r0 + self.h <= hi and c0 + self.w <= wi:
            win = frame[r0:r0 + self.h, c0:c0 + self.w]
        else:
            rows = np.clip(v + self._ar_h, 0, hi - 1)
            cols = np.clip(u + self._ar_w, 0, wi - 1)
            win = frame[rows[:, None], cols[None, :]]
        if win.ndim == 3:
            win = red_response(np.ascontiguousarray(win))
        return win.astype(np.float64)

    def _prior_f(self, frame: np.ndarray, c: np.ndarray) -> np.ndarray:
        key = (id(frame), int(c[0]), int(c[1]))
        if self._last_prior is not None and self._last_prior[0] == key:
            return self._last_prior[1]  # learning where it detected: the very same window
        prior_f = self._spectrum(self._window(frame, c))
        self._last_prior = (key, prior_f)
        return prior_f

    def _spectrum(self, win: np.ndarray) -> np.ndarray:
        return _rfft2((win - win.mean()) * self.weight)  # eq. 4-5 (context_prior)

    # ------------------------------------------------------------------ STC
    def _learn(self, frame: np.ndarray, centre: np.ndarray, rho_scale: float) -> None:
        """Eq. 8-9 at ``centre`` (STC.learn), applied by :meth:`idle` or the next step: only
        the window is cut now (the caller may reuse the frame's buffer)."""
        r = np.floor(centre + 0.5)
        key = (id(frame), int(r[0]), int(r[1]))
        centre = np.array(centre, dtype=float)
        if self._last_prior is not None and self._last_prior[0] == key:
            self._pending.append((None, self._last_prior[1], centre, rho_scale))
        else:
            self._pending.append((self._window(frame, r), None, centre, rho_scale))

    def idle(self) -> None:
        """Apply the learning left from the last step or re-anchoring (the context model the
        next frame is searched with). :meth:`step` does it first if nobody did; the live loop
        calls this between frames, after its command is out, where it costs nothing on the
        frame -> command path. Same numbers either way."""
        pending, self._pending = self._pending, []
        for win, prior_f, centre, rho_scale in pending:
            if prior_f is None:
                assert win is not None  # a step queues its window or its prior spectrum
                prior_f = self._spectrum(win)
            self._apply_learn(prior_f, centre, rho_scale)
        if pending:
            self._model()  # the next detection's model, made now

    def _apply_learn(self, prior_f: np.ndarray, centre: np.ndarray, rho_scale: float) -> None:
        r = np.floor(centre + 0.5)
        d = centre - r  # the target's sub-pixel place in the integer crop (fourier_shift)
        ramp = np.exp(1j * (d[1] * self._fy))[:, None] * np.exp(1j * (d[0] * self._fx))[None]
        if self.reg > 0:  # learn_spatial_context_reg
            power = prior_f.real * prior_f.real + prior_f.imag * prior_f.imag
            h_f = (self.conf_f * ramp) * np.conj(prior_f) / (power + power.mean() * self.reg
                                                              + self.eps)
        else:
            h_f = (self.conf_f * ramp) / (prior_f + self.eps) if self.eps else \
                (self.conf_f * ramp) / prior_f
        self.frame += 1
        if self.frame == 1:
            self.H_f = h_f
        else:
            self.H_f = self.H_f + (self.rho * rho_scale) * (h_f - self.H_f)
        if self.anchor > 0 and self.frame <= self.anchor_frames:  # the start model
            self.H_ref = self.H_f if self.frame == 1 else \
                self.H_ref + (self.H_f - self.H_ref) / self.frame

    def _model(self) -> np.ndarray:
        """The context model detection runs with: ``H_f``, pulled ``anchor`` of the way to
        the start model ``H_ref``; made once per learning step (:meth:`idle` makes it
        between frames, off the frame's path)."""
        H_f, H_ref = self.H_f, self.H_ref
        assert H_f is not None  # (set by init)
        if not (self.anchor > 0 and H_ref is not None):
            return H_f
        key = (id(H_f), id(H_ref))
        if self._anchored is None or self._anchored[0] != key:
            # (keyed by the two arrays: each learning step makes new ones, kept alive here)
            self._anchored = (key, H_f + self.anchor * (H_ref - H_f), H_f, H_ref)
        return self._anchored[1]

    def _detect(self, frame: np.ndarray, centre: np.ndarray
                ) -> tuple[np.ndarray, float, float, int, float]:
        """Eq. 10-11 around ``centre``: (uv, psr, second_ratio, n_peaks, peak)."""
        base = np.floor(centre + 0.5)
        resp = _irfft2(self._model() * self._prior_f(frame, base), (self.h, self.w))
        off_u, off_v, peak, psr, second_ratio, n_peaks = self._peak_quality(
            resp, self._e, self._even, self._eb)
        off = np.array([off_u, off_v])
        return base + off, psr, second_ratio, n_peaks, peak

    # ------------------------------------------------------------------ API
    def init(self, frame: np.ndarray, uv0: np.ndarray) -> None:
        """Start at ``uv0`` (2,) in ``frame`` (EAKFSTC.init_state)."""
        frame = self._frame(frame)
        hi, wi = frame.shape[:2]
        uv0 = np.asarray(uv0, float).reshape(-1)
        if uv0.shape != (2,) or not np.all(np.isfinite(uv0)) or not (
                -0.5 <= uv0[0] <= wi - 0.5 and -0.5 <= uv0[1] <= hi - 0.5):
            raise InputError(f"uv0: the start (u, v) = {uv0.tolist()} is not a point "
                             f"inside the {wi} x {hi} frame")
        self.x = np.stack([uv0, np.zeros(2), uv0, np.zeros(2)], axis=-1)  # eakf_init
        self.P = np.zeros((2, 4, 4))
        self.P[:, range(4), range(4)] = self.p0
        self.Z = np.stack([uv0, np.zeros(2)], axis=-1)
        self.s = np.array([[1.0, 1e6], [1.0, 1e6]])  # UNKNOWN_SCALE on the first displacement
        self.s_ref = np.ones(2)
        self.x_post = None
        self.H_f, self.H_ref, self.frame = None, None, 0
        self._last_prior = None
        self._pending = []
        self._learn(frame, uv0, 1.0)
        self._last_prior = None
        self.idle()
        self.coast, self.status = 0, int(TrackStatus.TRACKED)

    @property
    def uv(self) -> np.ndarray:
        """(2,) position estimate at the newest frame."""
        if self.x is None:
            raise InputError("LiteEAKFSTC.uv: call init(frame, uv0) first")
        return self.x[:, 0].copy()

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, int, dict[str, float | np.ndarray]]:
        """One EAKF-STC step (EAKFSTC.step_state): (uv (2,), status, quality)."""
        if self.H_f is None:
            raise InputError("LiteEAKFSTC.step: call init(frame, uv0) first")
        assert (self.x is not None and self.P is not None and self.Z is not None
                and self.s is not None and self.s_ref is not None)  # set by init, with H_f
        frame = self._frame(frame)
        self.idle()  # the last step's learning, if nobody applied it between frames
        hi, wi = frame.shape[:2]
        Phi, x, P = self.Phi, self.x, self.P
        pred = (Phi[:, 0, :] * x).sum(axis=-1)                             # 1. prediction
        centre = np.minimum(np.maximum(pred, 0.0), [wi - 1.0, hi - 1.0])
        z, psr, second_ratio, n_peaks, peak = self._detect(frame, centre)  # 2. measurement
        # 3. innovation of the delayed update (eakf_innovation, eq. 21-25)
        Z_new = np.empty((2, 2))  # (np.stack's values without its overhead, here and below)
        Z_new[:, 0] = z
        Z_new[:, 1] = z - self.Z[:, 0]
        nu = Z_new - self.psi * self.Z - (self.H_star @ x[..., None])[..., 0]
        PHt = P @ self.H_star.transpose(0, 2, 1)
        HPHt = self.H_star @ PHt
        noise = self.psi ** 2 * (self.s - 1.0)
        # the gate's scale on the position rows is 1 (its velocity rows' max(s_ref, 1) are
        # not read)
        S_pos = HPHt[:, 0, 0] + self.R[:, 0] * (1.0 + noise[:, 0])
        d2 = float((nu[:, 0] ** 2 / S_pos).sum())
        spread = max(float(S_pos.prod()), 0.0) ** 0.25
        # 4. drift guard (DriftGuard.forward)
        c = self.c
        l_psr = c[0] * (math.log(max(psr, _TINY)) - c[1])
        l_sec = c[2] * (c[3] - second_ratio)
        l_gate = c[4] * (c[5] - math.sqrt(d2 + 1e-12)) - c[6] * (math.log(max(spread, _TINY))
                                                                 - c[7])
        trust = _sigmoid(l_psr) * _sigmoid(l_sec) * _sigmoid(l_gate)
        r_scale = math.exp(c[8] * _sigmoid(c[11] * (c[12] - trust)))
        rho_scale = _sigmoid(c[9] * (trust - c[10]))
        # 5. update (eakf_update, eq. 25-26), the kept measurement blended by trust
        s_new = np.empty((2, 2))
        s_new[:, 0] = r_scale
        s_new[:, 1] = np.maximum(r_scale, self.s_ref)
        sc = s_new[:, 0].copy()
        S = HPHt.copy()
        add = self.R * (s_new + noise)
        S[:, 0, 0] += add[:, 0]
        S[:, 1, 1] += add[:, 1]
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        S_inv = np.empty((2, 2, 2))
        S_inv[:, 0, 0], S_inv[:, 0, 1] = S[:, 1, 1], -S[:, 0, 1]
        S_inv[:, 1, 0], S_inv[:, 1, 1] = -S[:, 1, 0], S[:, 0, 0]
        S_inv /= det[:, None, None]
        K = PHt @ S_inv
        x_post = x + (K @ nu[..., None])[..., 0]
        P_post = P - K @ PHt.transpose(0, 2, 1)
        self.x = (Phi @ x_post[..., None])[..., 0]
        P = Phi @ P_post @ Phi.transpose(0, 2, 1) + self.GQG
        self.P = 0.5 * (P + P.transpose(0, 2, 1))
        drop = 1.0 - trust
        self.Z = Z_new - drop * nu
        self.s = s_new - drop * (s_new - 1.0)
        self.s_ref = sc
        self.x_post = x_post
        uv = self.x[:, 0].copy()
        self._learn(frame, uv, rho_scale)                                  # 6. re-centre, learn
        self._last_prior = None
        std = math.sqrt(max(float(self.P[:, 0, 0].max()), 0.0))           # 7. status
        distrusted = int(trust < 0.5)
        self.coast = (self.coast + 1) * distrusted
        lost = self.coast > self.max_coast or std > self.lost_std
        self.status = int(TrackStatus.LOST) if lost else distrusted
        return uv, self.status, {"z": z, "trust": trust, "psr": psr,
                                 "second_ratio": second_ratio, "n_peaks": n_peaks,
                                 "peak": peak, "d2": d2, "r_scale": r_scale,
                                 "rho_scale": rho_scale, "std": std}

    def reanchor(self, frame: np.ndarray, uv: np.ndarray, rate: float = 1.0) -> None:
        """Move onto an absolute fix ``uv`` (2,) of the newest frame (EAKFSTC.reanchor)."""
        if self.H_f is None:
            raise InputError("LiteEAKFSTC.reanchor: call init(frame, uv0) first")
        assert self.x is not None and self.Z is not None  # set by init, with H_f
        frame = self._frame(frame)  # every check before the state moves
        uv = np.asarray(uv, float).reshape(-1)
        if uv.shape != (2,) or not np.all(np.isfinite(uv)):
            raise InputError(f"reanchor: uv must be 2 finite numbers, got {uv.tolist()}")
        d = uv - self.x[:, 0]
        for a in (self.x, self.x_post):
            if a is not None:
                a[:, 0] += d   # u(k) and u(k-1) together: the velocity is kept
                a[:, 2] += d
        self.Z[:, 0] += d
        self._last_prior = None  # a fix may come on a frame other than the last step's
        self._learn(frame, uv, rate / self.rho)
        self._last_prior = None
        self.coast, self.status = 0, int(TrackStatus.TRACKED)


class LiteTracker(Tracker):
    """EAKF-STC for one stream: the fitted module's parameters run by its numpy twin
    :class:`LiteEAKFSTC` (same equations, a third of the time at B = 1,
    where the module's tensor-op dispatch dominates)."""

    name = "eakf-stc"

    def __init__(self, module: EAKFSTC) -> None:
        self.lite = LiteEAKFSTC.from_module(module)
        self.fitted_fps = module.eakf.frame_rate

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.lite.init(frame, uv)

    def reanchor(self, frame: np.ndarray, uv: np.ndarray) -> None:
        """Move EAKF-STC onto an absolute fix ``uv`` of this (the newest) frame."""
        self.lite.reanchor(frame, uv)

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        uv, status, _ = self.lite.step(frame)
        return uv, status

    def idle(self) -> None:
        """Between frames: the context learning of the last update (see LiteEAKFSTC.idle)."""
        self.lite.idle()
