"""The live tracker: EAKF-STC with TIPM as an absolute anchor, fused by a Kalman filter on the
point, with its status decided from image evidence; one differentiable module fitted end to end.

Per frame (:class:`AnchoredFilter`, one stream):

1. EAKF-STC tracks (the inner tracker);
2. the fusion filter predicts the point, ``x <- x``, ``P <- P + Q`` (a random walk), or takes
   the robot's expected pixel (:meth:`AnchoredTracker.expect`);
3. TIPM looks for the stripe corner in a window around the prediction, its arm fits pulled
   toward the arm shape of the last fix taken where the corner was seen (:func:`observe`; a
   corner extrapolated under glare has the prior's own shape, see :meth:`AnchoredFilter.step`);
4. the corner is a measurement ``z`` with covariance ``R = g (s max(rms, floor))^2 M``
   (:func:`corner_cov_shape` gives ``M``, the glare term ``g`` is
   ``1 + (relu(glare - glare_start) / glare_scale)^2``), taken through a Mahalanobis gate:
   ``y = z - x``, ``S = P + R``, ``K = P S^-1``, ``x <- x + K y``, ``P <- (I - K) P``; a clean
   corner (inlier arm-fit RMS <= ``max_rms_px``) outside the gate restarts the filter there
   (``x <- z``, ``P <- R``: in closed loop the image jumps when the torch turns);
5. the EAKF-STC point is a weak measurement through its own gate;
6. EAKF-STC is re-anchored on the fused point when a fix was taken and it is more than
   ``reanchor_px`` off;
7. status from evidence: ``tracked`` only when this frame's corner is seen (both arms reach
   it) within ``evidence_px`` of the point, and (offline, without the robot's prediction) is
   not the clean corner of step 4's restart: a jump is evidence once the next frame finds its
   corner there, its own frame reports the prediction the jump left, and a jump the next
   frame does not confirm is undone (the filter goes back to the track it left and fuses
   that frame from there); ``coasting`` otherwise; ``lost`` after
   ``lost_frames`` or ``lost_px`` of coasting. While coasting, TIPM searches the whole frame
   between frames and ``reacquire_frames`` consistent corners move the track (no lock-out).

The fusion is written once, over a tiny array backend (:class:`NumpyOps` for the live loop,
:class:`TorchOps` for fitting): the same code runs the robot and is differentiated. The
settings of steps 2-6 (noise levels, gates, glare weights, the clean-fix and re-anchor
thresholds) are :class:`AnchoredParams`'s parameters, fitted with EAKF-STC's by gradient descent
(``torchseam train``): the gates and thresholds are hard decisions in the forward pass and
straight-through sigmoids in the backward pass, so the fitted tracker *is* the one that runs.
The evidence rules of step 7 and TIPM's window and arm prior are settings
(``configs/anchor.yaml``): they define what counts as seeing the corner, not how to estimate it.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from torchseam.core import kalman
from torchseam.core.config import ConfigError, config_field, config_path, load_config, read_yaml
from torchseam.core.errors import TorchseamError
from torchseam.core.kernels import load_kernels
from torchseam.track import model_file
from torchseam.track.base import Fix, Tracker, TrackResult
from torchseam.track.fusion import EAKFSTC, FusionState, LiteTracker, TrackStatus
from torchseam.track.shallow import ShallowFix, shallow_corner
from torchseam.vision.tipm import (
    CLIPPED,
    SATURATED,
    Tipm,
    TipmConfig,
    TipmResult,
    arm_shape,
    beside_clipped,
    power_sums,
    quad_normal_adjugate,
    red_response,
    thin_clipped_runs,
)

__all__ = ["FITTED", "AnchorConfig", "AnchoredFilter", "AnchoredModel", "AnchoredParams",
           "AnchoredState", "AnchoredTracker", "FusionValues", "NumpyOps", "TorchOps",
           "arm_directions", "corner_cov", "corner_cov_shape", "corner_seen", "fitted_eakf_stc",
           "glare_level", "load_anchor_config", "load_anchored_model"]

log = logging.getLogger("torchseam.track")

#: TrackerConfig fields that add parameters to EAKF-STC: read from the model file
STRUCTURAL_STC = ("reg", "anchor", "anchor_frames")
#: the fusion's settings fitted by gradient descent (:class:`AnchoredParams`); the rest of
#: :class:`AnchorConfig` are settings
FITTED = ("motion_u_px", "motion_v_px", "track_u_px", "track_v_px", "fix_noise",
          "fix_floor_px", "fix_gate", "track_gate", "max_rms_px", "reanchor_px",
          "glare_start", "glare_scale")


@dataclass(frozen=True)
class FusionValues:
    """The fusion's values that a fit sets (:data:`FITTED`; px unless named): what
    :class:`AnchoredParams` holds. A tracker runs with those of its model file; the ones in
    ``configs/anchor.yaml`` (``start:``) are only where a fit starts."""

    reanchor_px: float = config_field(lo=0.0, lo_open=True)
    motion_u_px: float = config_field(lo=0.0, lo_open=True)
    motion_v_px: float = config_field(lo=0.0, lo_open=True)
    track_u_px: float = config_field(lo=0.0, lo_open=True)
    track_v_px: float = config_field(lo=0.0, lo_open=True)
    fix_noise: float = config_field(lo=0.0, lo_open=True)
    fix_floor_px: float = config_field(lo=0.0, lo_open=True)
    fix_gate: float = config_field(lo=0.0, lo_open=True)
    track_gate: float = config_field(lo=0.0, lo_open=True)
    max_rms_px: float = config_field(lo=0.0, lo_open=True)
    glare_start: float = config_field(lo=0.0, lo_open=True)
    glare_scale: float = config_field(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class AnchorConfig:
    """Settings of the live tracker (``configs/anchor.yaml``; px unless named). The values a fit
    sets are not among them: a tracker runs with those of its model file
    (:attr:`AnchoredModel.fusion`); ``start`` is where a fit starts from."""

    window_px: int = config_field(lo=16)
    arm_noise_px: float = config_field(lo=0.0, lo_open=True)
    slope_step: float = config_field(lo=0.0, lo_open=True)
    curvature_step: float = config_field(lo=0.0, lo_open=True)
    glare_px: int = config_field(lo=1)
    evidence_px: float = config_field(lo=0.0, lo_open=True)
    lost_frames: int = config_field(lo=1)
    lost_px: float = config_field(lo=0.0, lo_open=True)
    reacquire_frames: int = config_field(lo=1)
    reacquire_step_px: float = config_field(lo=0.0, lo_open=True)
    support_px: float = config_field(lo=0.0, lo_open=True)
    support_points: int = config_field(lo=1)
    shallow_noise: float = config_field(lo=0.0, lo_open=True)
    shallow_below_deg: float = config_field(lo=0.0, hi=180.0)
    shallow_min_deg: float = config_field(lo=0.0, hi=90.0)
    shallow_max_along_px: float = config_field(lo=0.0, lo_open=True)
    evidence_sigmas: float = config_field(lo=0.0, lo_open=True)
    velocity_frames: int = config_field(lo=2)
    velocity_points: int = config_field(lo=2)
    velocity_fade_frames: float = config_field(lo=0.0, lo_open=True)
    shallow_with_expected: bool = config_field()
    start: FusionValues = config_field()


def load_anchor_config(path: str | Path | None = None) -> AnchorConfig:
    """:class:`AnchorConfig` from ``path`` (default ``configs/anchor.yaml``). A value the fitted
    model sets (:data:`FITTED`) given among the settings is refused, naming the model file: it
    would do nothing (the model's replaces it)."""
    p = Path(path or config_path("anchor.yaml"))
    raw = read_yaml(p)
    given = [k for k in FITTED if isinstance(raw, dict) and k in raw]
    if given:
        raise ConfigError(
            f"{p}: {given[0]}: set by the fitted model {model_file.DEFAULT_MODEL}, not by this "
            f"file (the value in use: `torchseam config show anchor`); a fit's starting value "
            f"goes under start:, another value for the run needs a new fit "
            f"(`torchseam train-live`)")
    return load_config(AnchorConfig, p)


# --------------------------------------------------------------------------- TIPM's evidence

def corner_cov_shape(res: TipmResult, prior: np.ndarray | None = None,
                     arm_cols: tuple[float, float] = (5.0, 120.0)) -> np.ndarray:
    """(2, 2) covariance of a TIPM corner per unit arm-line noise: each arm line is off along
    its normal by 1 px; where the lines meet at a shallow angle the corner is weak along the
    stripe (mostly u) and firm across it.

    An arm whose centre-line points stop short of the corner (spatter across it, a dropout, a
    gap) is extrapolated to it: its variance there is scaled by its fit's leverage at the
    corner over a complete arm's (one point per column from ``arm_cols[0]`` to
    ``arm_cols[1]`` px from the corner: TIPM's ``corner_gap_px`` and ``fit_window_px``;
    ``prior``: the arm prior the fit used, see :meth:`Tipm.corner`), never below 1.
    """
    assert res.arms is not None and res.centre is not None
    xc = float(res.uv[0] - res.u0)
    # each arm's normal (-slope, 1), unit: in scalars (the same operations as the row norm of
    # a (2, 2) array, without its overhead)
    rows = []
    for a in res.arms:
        n0 = -(a[1] + 2 * a[2] * xc)
        length = math.sqrt(n0 * n0 + 1.0)
        rows.append((n0 / length, 1.0 / length))
    normals = np.array(rows)
    gap, window = arm_cols
    u = res.centre[:, 0] - res.u0  # sorted by u (TIPM's centre line is)
    cut = np.searchsorted(u, (-window, -gap, gap, window), side="left")
    cut[1], cut[3] = np.searchsorted(u, (-gap, window), side="right")
    full = _full_arm_sums(float(gap), float(window))
    var = np.empty(2)
    for side in range(2):
        x = u[cut[2 * side]:cut[2 * side + 1]]
        w = (0.0, 0.0) if prior is None else (float(prior[side, 2]), float(prior[side, 3]))
        # (fewer than 3 points: TIPM gives no corner then; if it did, the arm says ~nothing)
        ratio = (_leverage(power_sums(x), xc, w) / _leverage(full[side], xc, w)
                 if len(x) >= 3 else 1e6)
        var[side] = max(1.0, ratio)
    n_inv = _inv2(normals)
    return (n_inv * var) @ n_inv.T


def corner_cov(res: TipmResult, noise: float, floor_px: float,
               prior: np.ndarray | None = None,
               arm_cols: tuple[float, float] = (5.0, 120.0)) -> np.ndarray:
    """(2, 2) covariance of a TIPM corner whose arm lines are off along their normals by
    ``noise * max(rms, floor_px)``, ``rms`` the arm fits' over the points they kept
    (:attr:`TipmResult.inlier_rms_px`; see :func:`corner_cov_shape`)."""
    sigma = noise * max(res.inlier_rms_px, floor_px)
    return sigma * sigma * corner_cov_shape(res, prior, arm_cols)


def glare_level(frame: np.ndarray, uv: np.ndarray, half_px: int) -> float:
    """Red glare around a point: the median red response (:func:`red_response`, grey levels)
    of the ``(2 half_px + 1)^2`` box of BGR ``frame`` (H, W, 3) centred at ``uv``; 0 where the box
    leaves the frame entirely. The stripe covers a few rows of the box, so the median is the
    background: arc light reflected off the part, which is red-heavy near the weld pool.

    Example:
        >>> f = np.zeros((100, 100, 3), np.uint8); f[..., 2] = 80   # a red haze
        >>> glare_level(f, np.array([50.0, 50.0]), 30)
        80.0
    """
    u, v = int(round(float(uv[0]))), int(round(float(uv[1])))
    box = frame[max(v - half_px, 0):max(v + half_px + 1, 0),
                max(u - half_px, 0):max(u + half_px + 1, 0)]
    if box.size == 0:
        return 0.0
    rank = box.shape[0] * box.shape[1] // 2
    if box.dtype == np.uint8 and (box.ndim == 2 or box.shape[2] == 3):
        # counted in one compiled pass over the box (the numbers of np.partition below)
        k = load_kernels(__package__)
        return float(k.colour_median_red(box, rank) if box.ndim == 3
                     else k.mono_median(box, rank))
    red = red_response(np.ascontiguousarray(box)).ravel()
    return float(np.partition(red, rank)[rank])


def arm_directions(res: TipmResult) -> np.ndarray:
    """(2, 2) unit image directions (du, dv) of the left and the right arm leaving a found
    corner: the tangents of TIPM's arm fits where they meet (fitted to every centre-line column
    of an arm, tighter than ECAL's few circle crossings; see docs/benchmarks.md).

    Example:
        >>> d = arm_directions(tipm(frame))  # doctest: +SKIP
    """
    s_left, s_right = arm_shape(res)[:, 0]  # dv / du of each arm at the corner
    d = np.array([[-1.0, -s_left], [1.0, s_right]])  # the left arm leaves towards -u
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@functools.lru_cache(maxsize=8)
def _full_arm_sums(gap: float, window: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Power sums of a complete left and right arm: one point per column ``gap..window`` px
    from the corner."""
    n, s1, s2, s3, s4 = power_sums(np.arange(np.ceil(gap), np.floor(window) + 1))
    return (n, -s1, s2, -s3, s4), (n, s1, s2, s3, s4)


def _leverage(sums: tuple[float, ...], xc: float, w: tuple[float, float]) -> float:
    """Variance, per unit point noise, of a quadratic fit at ``xc`` to columns with power sums
    ``sums``, ridge weights ``w`` on slope and curvature: ``e^T A^-1 e`` with
    ``e = (1, xc, xc^2)`` and ``A`` the 3x3 normal matrix."""
    (A00, A01, A02, A11, A12, A22), det = quad_normal_adjugate(sums, w)
    e1, e2 = xc, xc * xc
    q = (A00 + A11 * e1 * e1 + A22 * e2 * e2
         + 2.0 * (A01 * e1 + A02 * e2 + A12 * e1 * e2))
    return q / det


def _inv2(A: np.ndarray) -> np.ndarray:
    """Inverse of a (2, 2) matrix in closed form (np.linalg costs ~20 us a call on these)."""
    (a, b), (c, d) = A.tolist()
    det = a * d - b * c
    return np.array([[d, -b], [-c, a]]) / det


def corner_seen(res: TipmResult, support_px: float, points: int) -> bool:
    """Whether the stripe is seen at a found corner: each arm has at least ``points``
    centre-line points within ``support_px`` columns of it. A corner whose arms stop short
    (glare or a gap over it) is extrapolated: a good estimate, but no evidence that the stripe
    bends there.

    Example:
        >>> from torchseam.vision.tipm import load_tipm
        >>> u = np.arange(0.0, 200)
        >>> r = load_tipm().corner(np.stack([u, 100 - np.abs(u - 100) * 0.5], axis=1))
        >>> corner_seen(r, 10.0, 5)
        True
    """
    if res.centre is None or not len(res.centre):
        return False
    d = res.centre[:, 0] - res.uv[0]
    return bool(np.sum((d < 0) & (d >= -support_px)) >= points
                and np.sum((d > 0) & (d <= support_px)) >= points)


def blind_status(cfg: AnchorConfig, coast: int, out: np.ndarray,
                 last_evidence: np.ndarray | None) -> int:
    """The status of a point ``out`` (2,) on a frame without evidence, the ``coast``-th in a
    row: ``lost`` after ``lost_frames`` such frames or once ``lost_px`` from the last point
    with evidence (or without one, or a point that is not finite), ``coasting`` before."""
    far = (last_evidence is None or not np.all(np.isfinite(out))
           or float(np.linalg.norm(out - last_evidence)) > cfg.lost_px)
    return int(TrackStatus.LOST if far or coast > cfg.lost_frames else TrackStatus.COASTING)


@dataclass
class Observation:
    """What TIPM saw on one frame in the window around the prediction.

    Attributes:
        glare: :func:`glare_level` around the prediction (grey levels).
        stripe: ``(response, mask, (x0, y0))`` of the window, or None (window off the frame).
        res: the corner fit (window coordinates), or None (no corner).
        z: (2,) the corner, frame px (None without one). shape_cov: (2, 2)
            :func:`corner_cov_shape` of it.
        seen: :func:`corner_seen`.
        shallow: where TIPM gave no corner on a stripe it saw: the corner read from the
            slope break over both arms' whole length (:func:`shallow_corner`, frame px), its
            ``cov`` per unit noise factor, along-stripe std capped at
            ``shallow_max_along_px`` and set to that cap below ``shallow_min_deg`` of kink
            (a straight stripe says where the line is, not where along it the corner is).
        shallow_seen: both arms have centre-line points next to the shallow corner.
        shallow_outside: none of the shallow corner's centre-line points lies in the glare
            box (``glare_px`` round the prediction).
    """

    glare: float
    stripe: tuple[np.ndarray, np.ndarray, tuple[int, int]] | None = None
    res: TipmResult | None = None
    z: np.ndarray | None = None
    shape_cov: np.ndarray | None = None
    seen: bool = False
    shallow: ShallowFix | None = None
    shallow_seen: bool = False
    shallow_outside: bool = False


def observe(tipm: Tipm, frame: np.ndarray, x: np.ndarray, prior: np.ndarray | None,
            cfg: AnchorConfig, shallow: bool = True) -> Observation:
    """TIPM in the ``window_px`` window of ``frame`` around the predicted point ``x`` (2,),
    its arm fits pulled toward ``prior`` (see :meth:`Tipm.corner`), and the glare there; with
    ``shallow``, the shallow corner where TIPM gives none or an extrapolated one (else TIPM's
    corner whenever it gives one)."""
    h, w = frame.shape[:2]
    cu, cv = float(x[0]), float(x[1])
    obs = Observation(glare_level(frame, x, cfg.glare_px))
    x0 = int(min(max(cu - cfg.window_px, 0), w - 1))  # (np.clip's value, ~10 us less)
    y0 = int(min(max(cv - cfg.window_px, 0), h - 1))
    roi = np.ascontiguousarray(frame[y0:int(cv) + cfg.window_px + 1,
                                     x0:int(cu) + cfg.window_px + 1])
    if roi.shape[0] < 16 or roi.shape[1] < 16:
        return obs
    # the frame is checked already; the stripe response and mask of the window are kept for
    # ECAL (TrackResult.stripe)
    res, red, mask = tipm.find(roi, prior)
    obs.stripe = (red, mask, (x0, y0))
    seen = res.ok and corner_seen(res, cfg.support_px, cfg.support_points)
    if res.ok and (seen or not shallow or 180.0 - res.corner_deg >= cfg.shallow_below_deg):
        t = tipm.cfg
        obs.res, obs.z = res, res.uv + (x0, y0)
        obs.shape_cov = corner_cov_shape(res, prior, (t.corner_gap_px, t.fit_window_px))
        obs.seen = seen
    elif shallow and (res.centre is not None or roi.ndim == 2):
        # no corner, or a shallow one extrapolated over arms that stop short (glare on it):
        # TIPM's arm fits there lean on the prior's slopes, which a flattening kink no
        # longer has (a biased corner, its covariance too small); read it from the whole
        # arms instead
        centre = res.centre
        if roi.ndim == 2:
            # read by its brightness: the arms where they run clipped over glare, also in a
            # window refused as blinded (see clipped_centre); the points whose ridge reaches
            # into clipped light are that light's edge (a saturated glare core's rim), not
            # the stripe; the shallow corner takes what is left (the red excess of a colour
            # frame has no such rim)
            # TIPM's first look at a window not refused as blinded made the planes that the
            # window's unblinded reading makes (see clipped_centre)
            first = (red, mask) if res.first_look and res.reason != SATURATED else None
            centre, clipped = clipped_centre(tipm, roi,
                                             centre if res.reason != SATURATED else None, first)
            if centre is not None:
                keep = ~beside_clipped(roi, centre, tipm.cfg.ridge_px // 2)
                centre, clipped = centre[keep], clipped[keep]
        else:
            clipped = None
        if centre is not None:
            _observe_shallow(obs, centre, (x0, y0), prior, tipm, cfg, clipped)
            if obs.shallow is not None:
                near = np.abs(centre + (x0 - cu, y0 - cv)) <= cfg.glare_px
                obs.shallow_outside = not bool(np.any(near[:, 0] & near[:, 1]))
    return obs


@functools.lru_cache(maxsize=4)
def _unblinded(cfg: TipmConfig) -> Tipm:
    """A :class:`Tipm` of ``cfg`` that does not refuse a window as blinded."""
    return Tipm(dataclasses.replace(cfg, max_saturated_fraction=1.0))


def clipped_centre(tipm: Tipm, roi: np.ndarray, centre: np.ndarray | None,
                   planes: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> tuple[np.ndarray | None, np.ndarray]:
    """The centre line (N, 2) of a window ``roi`` (H, W) read by its brightness, with the
    stripe where it runs clipped over glare: ``centre``, TIPM's centre line of the window
    (None: TIPM refused it as blinded), where the window holds no thin clipped run
    (:func:`~torchseam.vision.tipm.thin_clipped_runs`: at most ``ridge_px // 2`` rows tall,
    a line the ridge filter would pass, in areas of ``min_area`` px at least); otherwise the
    stripe path (:meth:`Tipm.centre`) over TIPM's mask, the window not refused as blinded,
    with those runs added and weighed as the brightest response (their middle is the
    stripe's centre). Why: under a clipped glare core the stripe's arms run clipped over the
    bright halo round it, a few grey levels of ridge, and a window more than
    ``max_saturated_fraction`` clipped is refused whole, while the arms are still in view
    outside the core (docs/benchmarks.md, issue 35). ``planes``: the window's stripe response
    and mask (:meth:`Tipm.stripe_mask`) when TIPM made them without refusing it as blinded,
    the same as the unblinded reading's (then not made again: ~0.4 ms, issue 35); None: made
    here. Returns ``(centre or None, clipped (N,) bool: the points on a clipped run)``."""
    thin = thin_clipped_runs(roi, tipm.cfg.ridge_px // 2, tipm.cfg.min_area)
    if centre is not None and not thin.any():
        return centre, np.zeros(len(centre), bool)
    t = _unblinded(tipm.cfg)
    red, mask = t.stripe_mask(roi)[:2] if planes is None else planes
    pts = t.centre(cv2.max(red, thin), cv2.max(mask, thin))
    h, w = thin.shape
    u = np.clip(np.rint(pts[:, 0]).astype(np.intp), 0, w - 1)
    v = np.clip(np.rint(pts[:, 1]).astype(np.intp), 0, h - 1)
    return pts, thin[v, u] > 0


def _observe_shallow(obs: Observation, centre: np.ndarray, corner: tuple[int, int],
                     prior: np.ndarray | None, tipm: Tipm, cfg: AnchorConfig,
                     clipped: np.ndarray | None = None) -> None:
    """The shallow corner of the window's centre line ``centre`` (N, 2) (window px, its
    corner at ``corner`` in the frame) into ``obs``: the arms' curvatures pulled toward the
    arm prior's (they do not change as the kink flattens; the slopes do). ``clipped`` (N,)
    marks the points read off clipped runs (:func:`clipped_centre`): they place the arms but
    are no support for seeing the corner (a clipped cross-section is symmetric only where
    the light round it is even, and next to a glare-lit corner it is not)."""
    curv, w_c = (None, 0.0) if prior is None else (prior[:, 1], float(prior[0, 3]))
    sf = shallow_corner(centre, tipm.cfg.min_points_per_arm, curvature=curv,
                        curvature_weight=w_c, max_along_px=cfg.shallow_max_along_px)
    if sf is None:
        return
    if sf.kink_deg < cfg.shallow_min_deg:
        # too straight to say where along the stripe: the line only
        t = np.array([1.0, sf.slope]) / math.hypot(1.0, sf.slope)
        cov = sf.cov + (cfg.shallow_max_along_px ** 2 - sf.along_px ** 2) * np.outer(t, t)
        sf = dataclasses.replace(sf, cov=cov)
    sf = dataclasses.replace(sf, uv=sf.uv + corner)
    obs.shallow = sf
    d = centre[:, 0] + corner[0] - sf.uv[0]
    if clipped is not None:
        d = d[~clipped]
    obs.shallow_seen = bool(np.sum((d < 0) & (d >= -cfg.support_px)) >= cfg.support_points
                            and np.sum((d > 0) & (d <= cfg.support_px)) >= cfg.support_points)


# --------------------------------------------------------------------------- array backends

class NumpyOps:
    """The fusion's arithmetic on numpy (the live loop): hard decisions, float64."""

    @staticmethod
    def const(a: Any) -> np.ndarray:
        return np.array(a, dtype=float)

    @staticmethod
    def value(a: Any) -> np.ndarray:
        return np.asarray(a, dtype=float)

    @staticmethod
    def diag2(a: Any, b: Any) -> np.ndarray:
        return np.array([[a, 0.0], [0.0, b]])

    inv2 = staticmethod(_inv2)

    @staticmethod
    def maximum(a: Any, b: float) -> Any:
        return max(a, b)

    @staticmethod
    def relu(a: Any) -> Any:
        return max(a, 0.0)

    @staticmethod
    def sqrt(a: Any) -> float:
        return math.sqrt(max(float(a), 0.0))

    @staticmethod
    def decide(hard: bool, margin: Any, temperature: float) -> float:
        """The weight of a yes/no decision: 1.0 or 0.0."""
        return 1.0 if hard else 0.0

    @staticmethod
    def blend(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
        """``b`` where ``w`` is 1, ``a`` where 0."""
        return b.copy() if w else a


class TorchOps:
    """The fusion's arithmetic on torch (fitting): the same forward values as
    :class:`NumpyOps`; a decision is its hard 0/1 value forward and a sigmoid of its margin
    backward (straight-through), so gates and thresholds get gradients."""

    def __init__(self, dtype: torch.dtype = torch.float64) -> None:
        self.dtype = dtype

    def const(self, a: Any) -> Tensor:
        return torch.as_tensor(np.asarray(a, dtype=float), dtype=self.dtype)

    @staticmethod
    def value(a: Tensor) -> np.ndarray:
        return a.detach().to(torch.float64).numpy()

    @staticmethod
    def diag2(a: Tensor, b: Tensor) -> Tensor:
        z = torch.zeros_like(a)
        return torch.stack([torch.stack([a, z]), torch.stack([z, b])])

    @staticmethod
    def inv2(A: Tensor) -> Tensor:
        a, b, c, d = A[0, 0], A[0, 1], A[1, 0], A[1, 1]
        return torch.stack([torch.stack([d, -b]), torch.stack([-c, a])]) / (a * d - b * c)

    def maximum(self, a: Tensor | float, b: float) -> Tensor:
        return torch.clamp(torch.as_tensor(a, dtype=self.dtype), min=b)

    @staticmethod
    def relu(a: Tensor) -> Tensor:
        return torch.relu(a)

    @staticmethod
    def sqrt(a: Tensor) -> Tensor:
        return torch.sqrt(torch.clamp(a, min=1e-12))

    @staticmethod
    def decide(hard: bool, margin: Tensor | float, temperature: float) -> Tensor | float:
        if not isinstance(margin, Tensor) or not margin.requires_grad:
            return 1.0 if hard else 0.0
        soft = torch.sigmoid(margin / temperature)
        return (1.0 if hard else 0.0) + soft - soft.detach()

    @staticmethod
    def blend(a: Tensor, b: Tensor, w: Tensor | float) -> Tensor:
        return a + w * (b - a)


def _num(x: Any) -> float:
    """A backend scalar as a float (no gradient)."""
    return float(x.detach()) if isinstance(x, Tensor) else float(x)


#: temperatures of the straight-through decisions (the margin's units: sigma, px, px)
GATE_TEMP, RMS_TEMP, REANCHOR_TEMP = 0.5, 0.05, 0.5


@dataclass
class LeftState:
    """What the filter held on a frame where it restarted on a clean corner outside its gate
    (the jump), had it not: its prediction ``x``, ``P`` there, the arm shape of its last
    seen fix and that fix's age, the frame count, and its motion trail. The next frame's
    evidence decides between the jump and this (:meth:`AnchoredFilter.step`)."""

    x: Any
    P: Any
    shape: np.ndarray | None
    age: int
    k: int
    trail: list[tuple[int, np.ndarray]]

    def detached(self) -> LeftState:
        """The same, cut from the graph (torch backend; truncated BPTT)."""
        return dataclasses.replace(self, x=self.x.detach(), P=self.P.detach())


# --------------------------------------------------------------------------- one stream

class AnchoredFilter:
    """The fusion and the evidence rules of one stream (see the module docstring), on an array
    backend (:class:`NumpyOps` or :class:`TorchOps`) with the fitted values ``params`` (the
    names of :data:`FITTED`: floats, or 0-d tensors for fitting).

    The caller runs the inner tracker: :meth:`step` takes its point of this frame, returns the
    fused point and how much to re-anchor the inner tracker onto it.
    """

    def __init__(self, cfg: AnchorConfig, tipm: Tipm, params: Mapping[str, Any],
                 ops: Any = NumpyOps) -> None:
        self.cfg, self.tipm, self.ops = cfg, tipm, ops
        self.set_params(params)
        self.x: Any = None               # filtered point (u, v)
        self.P: Any = None
        self.shape: np.ndarray | None = None   # arm_shape of the last fix taken and seen
        self.age = 0                           # frames since that fix
        self.coast = 0                         # frames without evidence in a row
        self.last_evidence: np.ndarray | None = None
        self.status = int(TrackStatus.TRACKED)
        self._found: list[np.ndarray] = []     # whole-frame corners in a row (see search)
        self._reacquire: np.ndarray | None = None
        self.reacquired = 0  # times the track was moved onto persistent independent corners
        self.innovation: kalman.Innovation | None = None  # the last measurement's
        self.k = 0                                   # frames stepped
        self._trail: deque[tuple[int, np.ndarray]] = deque()  # (frame, point) with evidence
        self._velocity: np.ndarray | None = None     # (2,) px per frame, from the trail ...
        self._velocity_due = False                   # ... fitted again when next asked
        self.left: LeftState | None = None  # the state the last frame's jump left, if any

    def set_params(self, params: Mapping[str, Any]) -> None:
        """New fitted values (after an optimiser step)."""
        p, o = params, self.ops
        self.p = dict(params)
        self.Q = o.diag2(p["motion_u_px"] ** 2, p["motion_v_px"] ** 2)
        self.I = o.const(np.eye(2))  # F and H: a random walk, the point measured directly
        self.R_track = o.diag2(p["track_u_px"] ** 2, p["track_v_px"] ** 2)

    def detach(self, params: Mapping[str, Any]) -> None:
        """Cut the state from the graph (truncated BPTT) and take new fitted values."""
        self.x, self.P = self.x.detach(), self.P.detach()
        if self.left is not None:
            self.left = self.left.detached()
        self.set_params(params)

    def _restart(self, uv: Any, P: Any, shape: np.ndarray | None) -> None:
        self.x, self.P = uv, P
        self.shape, self.age = shape, 0

    def start(self, uv: np.ndarray) -> None:
        """Start at ``uv`` (2,) (the inner tracker's start)."""
        self._restart(self.ops.const(uv), self.Q, None)
        self.coast, self.last_evidence = 0, np.asarray(uv, float).copy()
        self.status = int(TrackStatus.TRACKED)
        self._found, self._reacquire, self.left = [], None, None
        self._forget_motion()

    def _forget_motion(self) -> None:
        """The track jumped (a start, a restart on a clean corner, a re-acquisition): the
        points before say nothing about its motion after."""
        self._trail.clear()
        self._velocity, self._velocity_due = None, False

    def _learn_motion(self, uv: np.ndarray) -> None:
        """A point with evidence joins the trail (the last ``velocity_frames`` frames'); the
        velocity is fitted from it when next asked (:attr:`velocity`)."""
        c = self.cfg
        self._trail.append((self.k, np.asarray(uv, float).copy()))
        while self._trail and self._trail[0][0] <= self.k - c.velocity_frames:
            self._trail.popleft()
        self._velocity_due = True

    @property
    def velocity(self) -> np.ndarray | None:
        """(2,) px per frame: the least-squares slope of the trail's points (at least
        ``velocity_points`` of them), per axis: ``v = sum (k - k_m)(x_k - x_m) /
        sum (k - k_m)^2``; None with fewer. Fitted only when asked (the trail changes only
        with evidence; the live loop, which has the robot's expected pixel, never asks)."""
        if self._velocity_due:
            self._velocity_due = False
            if len(self._trail) < self.cfg.velocity_points:
                self._velocity = None
            else:
                k = np.array([f for f, _ in self._trail], float)
                X = np.array([p for _, p in self._trail])
                dk = k - k.mean()
                self._velocity = dk @ (X - X.mean(axis=0)) / float(dk @ dk)
        return self._velocity

    def prior(self) -> np.ndarray | None:
        """The arm prior for TIPM: the arm shape of the last fix taken and seen, its variance
        grown by a random walk of ``slope_step`` / ``curvature_step`` per frame since."""
        if self.shape is None:
            return None
        c = self.cfg
        n = max(self.age, 1)
        out = np.empty((2, 4))
        out[:, :2] = self.shape
        out[:, 2] = c.arm_noise_px ** 2 / (n * c.slope_step ** 2)
        out[:, 3] = c.arm_noise_px ** 2 / (n * c.curvature_step ** 2)
        return out

    def _measure(self, z: Any, R: Any, gate: Any) -> bool:
        """Kalman update with ``z`` (covariance ``R``, ``H = I``) unless its Mahalanobis
        distance from the filtered point exceeds ``gate`` (:mod:`torchseam.core.kalman`)."""
        o = self.ops
        inn = kalman.innovation(self.x, self.P, z, self.I, R)
        self.innovation = inn
        hard = bool(_num(inn.d2) <= _num(gate) ** 2)
        w = o.decide(hard, gate - o.sqrt(inn.d2), GATE_TEMP)
        if isinstance(w, float) and w == 0.0:
            return False
        self.x, self.P = kalman.update(self.x, self.P, inn, self.I, R, w)
        return hard

    def step(self, frame: np.ndarray, inner_uv: Any, inner_ok: bool,
             expected: np.ndarray | None = None) -> tuple[Any, Any, Fix | None,
                                                           Observation]:
        """Fuse one frame.

        Offline (no robot prediction), a restart on the last frame on a clean corner outside
        the gate (the jump, :attr:`Fix.jumped`) holds only if this frame confirms it: its
        corner seen within ``evidence_px`` of the point (what makes a frame ``tracked``). Otherwise
        the filter goes back to the track the jump left (:class:`LeftState`) and fuses this
        frame from there: glare makes clean corners elsewhere on the stripe for a frame, and
        a point left there would coast on the wrong place for as long as the corner stays
        hidden. A genuine jump is lost by this only while its corner is not seen: the next
        frame it shows, it restarts the filter again.

        Args:
            frame: the frame (checked, canonical view).
            inner_uv: (2,) the inner tracker's point on it (an array of the backend).
            inner_ok: whether the inner tracker's point is a measurement (not lost, finite).
            expected: the robot's expected pixel for this frame, or None.

        Returns:
            ``(x, reanchor, fix, obs)``: the fused point (backend array), the weight (0/1
            forward) with which the inner tracker is to be moved onto it, the TIPM fix weighed
            (or None) and the observation.
        """
        robot = expected is not None  # the live loop: a prediction from the robot's motion
        left, self.left = self.left, None
        if self.x is None:
            self._restart(inner_uv, self.Q, None)
        if self._reacquire is not None:
            # a corner the whole-frame search found persistently away from the track
            # (see search): start again there; the window below looks for it on this frame
            self._restart(self.ops.const(self._reacquire), self.Q, None)
            self._reacquire, expected, left = None, None, None
            self.reacquired += 1
            self._forget_motion()
        x, reanchor, fix, obs = self._fuse(frame, inner_uv, inner_ok, expected, robot)
        if left is not None and not robot and not self.evidence(self.ops.value(x), fix):
            # the jump unconfirmed: back to the track it left, this frame fused from there;
            # EAKF-STC, moved onto the jump, is moved back onto the point
            self.x, self.P, self.shape, self.age, self.k = (left.x, left.P, left.shape,
                                                            left.age, left.k)
            self._trail = deque(left.trail)
            self._velocity_due = True
            self.left = None
            x, _, fix, obs = self._fuse(frame, inner_uv, inner_ok, None, robot)
            reanchor = 1.0
        return x, reanchor, fix, obs

    def _fuse(self, frame: np.ndarray, inner_uv: Any, inner_ok: bool,
              expected: np.ndarray | None, robot: bool
              ) -> tuple[Any, Any, Fix | None, Observation]:
        """Steps 2-6 of the module docstring on one frame (see :meth:`step`); ``robot``: the
        frame came with the robot's expected pixel (``expected`` may be None all the same: a
        re-acquisition drops it)."""
        o, c, p = self.ops, self.cfg, self.p
        self.age += 1
        self.k += 1
        # x <- F x + B u, P <- F P F^T + Q  (F = B = I; u the velocity of the points with
        # evidence, px per frame: the motion along the stripe goes on while the corner is
        # not seen; no velocity yet: a random walk)
        self.x, self.P = kalman.predict(self.x, self.P, self.I, self.Q)
        if expected is not None:
            self.x = o.const(expected)
        elif self.coast > 0 and self.velocity is not None:
            # the velocity fades while no evidence comes: the corner's image motion is no
            # constant velocity over tens of frames (the path's wobble, the part's deviation)
            fade = math.exp(-self.coast / self.cfg.velocity_fade_frames)
            self.x = self.x + o.const(fade * self.velocity)
        # the shallow corner only where no robot prediction comes (offline), unless set: in
        # the live loop the expected pixel places the point better (docs/benchmarks.md)
        obs = observe(self.tipm, frame, o.value(self.x), self.prior(), c,
                      shallow=expected is None or c.shallow_with_expected)
        inflate = 1.0 + (o.relu(obs.glare - p["glare_start"]) / p["glare_scale"]) ** 2
        taken, fix = False, None
        if obs.res is not None:
            rms = obs.res.inlier_rms_px
            sigma = p["fix_noise"] * o.maximum(p["fix_floor_px"], rms)
            cov = (sigma * sigma) * o.const(obs.shape_cov)
            R = inflate * cov
            z = o.const(obs.z)
            taken = self._measure(z, R, p["fix_gate"])
            clean = rms <= _num(p["max_rms_px"])
            # offline (no robot prediction): a jump off the track's own prediction; the live
            # loop's expected pixel is made afresh from the robot's motion every frame, and
            # its window, gate and the located points' confirmation stand against a jump
            jumped = not taken and clean and not robot
            if jumped:
                self.left = LeftState(self.x, self.P, self.shape, self.age, self.k,
                                      list(self._trail))
            if not taken:
                # a clean corner the motion model did not expect: the image jumped; a clean
                # fit is worth more than the random-walk prediction, so start again there
                w = o.decide(clean, p["max_rms_px"] - rms, RMS_TEMP * _num(p["max_rms_px"]))
                if clean or not isinstance(w, float):
                    self.x = o.blend(self.x, z, w)
                    self.P = o.blend(self.P, R, w)
                if clean:
                    self._forget_motion()
                taken = clean
            if taken and obs.seen:
                # the prior learns only from a corner the image shows: one extrapolated over
                # arms that stop short (glare over the corner) has the prior's own shape, and
                # taking it as the next prior would keep a bent prior for as long as the
                # corner is hidden and bias the fixes after it
                self.shape, self.age = arm_shape(obs.res), 0
            assert obs.z is not None  # set with obs.res
            fix = Fix(obs.z.copy(), o.value(cov), _num(inflate), taken, obs.seen,
                      jumped=jumped)
        elif obs.shallow is not None:
            # a nearly straight stripe: its slope break places the corner weakly along the
            # stripe, firmly across it (R from the fit, c.shallow_noise for the centre line's
            # errors correlated along the stripe); gated like a fix, never a restart
            sf = obs.shallow
            cov = (c.shallow_noise ** 2) * sf.cov
            # the glare term weighs what the light round the prediction does to the points
            # a fix is read from; where that box is mostly clipped (its median at the
            # clipping level: a glare core over the corner) and no point of the fit lies in
            # it, the fix is the arms' outside it, and its own fit says how well
            g = 1.0 if obs.glare >= CLIPPED and obs.shallow_outside else inflate
            taken = self._measure(o.const(sf.uv), g * o.const(cov), p["fix_gate"])
            # evidence only when the image places it within the evidence radius; firm (a
            # located point for the robot's expected pixel) when its std along the stripe,
            # glare included, is within it
            along = sf.along_px
            seen = obs.shallow_seen and c.evidence_sigmas * along * c.shallow_noise \
                <= c.evidence_px
            firm = along * c.shallow_noise * math.sqrt(_num(g)) <= c.evidence_px
            fix = Fix(sf.uv.copy(), cov, _num(g), taken, seen, shallow=True, firm=firm)
        if inner_ok:
            self._measure(inner_uv, inflate * self.R_track, p["track_gate"])
        reanchor: Any = 0.0
        if taken:
            if not inner_ok:
                reanchor = 1.0
            else:
                dist = o.sqrt(((self.x - inner_uv) ** 2).sum())
                reanchor = o.decide(_num(dist) > _num(p["reanchor_px"]),
                                    dist - p["reanchor_px"], REANCHOR_TEMP)
        return self.x, reanchor, fix, obs

    def reported(self, x: Any) -> Any:
        """The point to report for this frame, given its fused point ``x``: ``x``, but on a
        frame where the filter jumped to a clean corner outside its gate (offline, unconfirmed
        until the next frame: see :meth:`step`) the prediction the jump left. The filter
        follows the jump; what is reported waits for the next frame to confirm it, so a
        corner glare made for one frame tens of px away is never the frame's point (a genuine
        jump is reported one frame late). Offline only: the live loop, which predicts the
        point from the robot's motion, takes each frame's fused point (its located points of
        coasting frames wait for the next evidence anyway)."""
        return x if self.left is None else self.left.x

    def evidence(self, out: np.ndarray, fix: Fix | None) -> bool:
        """Whether ``fix`` is evidence for the point ``out`` (2,): seen, within
        ``evidence_px`` of it, and not a corner the filter jumped to on this frame (that is
        evidence only when the next frame finds it again: under glare a clean corner tens of
        px from a track that was right)."""
        return fix is not None and fix.seen and not fix.jumped and float(
            np.linalg.norm(fix.uv - out)) <= self.cfg.evidence_px

    def verdict(self, out: np.ndarray, fix: Fix | None) -> int:
        """This frame's status from the evidence at ``out`` (2,) (see the module docstring)."""
        c = self.cfg
        if self.evidence(out, fix):
            self.coast, self.last_evidence = 0, np.asarray(out, float).copy()
            self.status = int(TrackStatus.TRACKED)
            self._learn_motion(out)
        else:
            self.coast += 1
            self.status = blind_status(c, self.coast, out, self.last_evidence)
        return self.status

    def search(self, frame: np.ndarray | None) -> None:
        """Between frames, while the track has no evidence: TIPM on the whole frame without
        the prior; ``reacquire_frames`` corners in a row, each within ``reacquire_step_px`` of
        the one before and away from the track, move the next frame's track there. No gate
        may hold a wrong track forever."""
        if frame is None or self.status == TrackStatus.TRACKED:
            self._found.clear()
            return
        c = self.cfg
        res = self.tipm(frame)
        x = None if self.x is None else self.ops.value(self.x)
        if (not res.ok or not corner_seen(res, c.support_px, c.support_points)
                or (x is not None and np.linalg.norm(res.uv - x) <= c.evidence_px)):
            self._found.clear()
            return
        if self._found and np.linalg.norm(res.uv - self._found[-1]) > c.reacquire_step_px:
            self._found.clear()
        self._found.append(res.uv)
        if len(self._found) >= c.reacquire_frames:
            self._reacquire, self._found = res.uv, []


# --------------------------------------------------------------------------- the module

class AnchoredParams(nn.Module):
    """The fusion's fitted values (:data:`FITTED`), kept as logarithms (all are positive).

    Example:
        >>> f = AnchoredParams(load_anchor_config().start)
        >>> round(float(f.natural()["fix_gate"]), 3)
        4.0
    """

    def __init__(self, start: FusionValues, learnable: bool = False) -> None:
        super().__init__()
        for name in FITTED:
            t = torch.tensor(math.log(float(getattr(start, name))), dtype=torch.float64)
            if learnable:
                self.register_parameter(f"log_{name}", nn.Parameter(t))
            else:
                self.register_buffer(f"log_{name}", t)

    def natural(self) -> dict[str, Tensor]:
        """The values in their units (0-d tensors, differentiable)."""
        return {n: getattr(self, f"log_{n}").exp() for n in FITTED}

    def values(self) -> dict[str, float]:
        """The values in their units, as floats."""
        return {n: float(v.detach()) for n, v in self.natural().items()}


@dataclass
class AnchoredState:
    """B streams of :class:`AnchoredModel`: the inner EAKF-STC's batched state and one
    :class:`AnchoredFilter` per stream (torch backend)."""

    inner: FusionState
    filters: list[AnchoredFilter]
    frames: list[np.ndarray | None]  # this step's frames, for the between-frames search


class AnchoredModel(nn.Module):
    """The live tracker as one module: EAKF-STC (``eakf_stc``) and the fusion's fitted values
    (``fusion``). Its ``state_dict`` is the model file; :class:`AnchoredTracker` runs it on
    the live loop (numpy, one stream), :meth:`step_state` on B streams in torch for fitting.

    Args:
        eakf_stc: the inner tracker module.
        cfg: the settings; the fusion starts at ``cfg.start`` (a model file's
            :func:`~torchseam.track.model_file.load_fitted` then sets it).
        learnable: the fusion's values are parameters (else buffers).

    Example:
        >>> trk = AnchoredModel(EAKFSTC(), load_anchor_config())
        >>> sorted(trk.fusion.values())[:2]
        ['fix_floor_px', 'fix_gate']
    """

    def __init__(self, eakf_stc: EAKFSTC, cfg: AnchorConfig, learnable: bool = False
                 ) -> None:
        super().__init__()
        self.eakf_stc = eakf_stc
        self.fusion = AnchoredParams(cfg.start, learnable)
        self.cfg = cfg

    @property
    def config(self) -> Any:
        """The inner tracker's configuration (what the model file records)."""
        return self.eakf_stc.config

    # ------------------------------------------------------------------ batched (fitting)
    def _params(self) -> dict[str, Tensor]:
        dt = self.eakf_stc.eakf.dt.dtype
        return {k: v.to(dt) for k, v in self.fusion.natural().items()}

    def init_state(self, frames: Sequence[np.ndarray], grey: Tensor, uv0: Tensor,
                   tipm: Tipm) -> AnchoredState:
        """Start B streams at ``uv0`` (B, 2) on their first frames (``frames``: B colour or
        mono frames; ``grey``: (B, H, W) their stripe response, what EAKF-STC sees; ``tipm``:
        the fixes' TIPM, the live loop's)."""
        inner = self.eakf_stc.init_state(grey, uv0)
        ops = TorchOps(self.eakf_stc.eakf.dt.dtype)
        params = self._params()
        filters = []
        for i in range(len(frames)):
            f = AnchoredFilter(self.cfg, tipm, params, ops)
            f.start(uv0[i].detach().to(torch.float64).numpy())
            filters.append(f)
        return AnchoredState(inner, filters, [None] * len(frames))

    def detach(self, state: AnchoredState) -> AnchoredState:
        """Cut the state from the graph (truncated BPTT) with the current fitted values."""
        params = self._params()
        for f in state.filters:
            f.detach(params)
        return AnchoredState(self.eakf_stc.detach(state.inner), state.filters, state.frames)

    def step_state(self, state: AnchoredState, frames: Sequence[np.ndarray], grey: Tensor
                   ) -> tuple[AnchoredState, Tensor, list[int]]:
        """One frame of B streams (as :meth:`AnchoredTracker.track`, per stream).

        Returns:
            (state, fused points (B, 2) with gradient, statuses).
        """
        for f, fr in zip(state.filters, state.frames, strict=True):
            f.search(fr)  # the last frame's between-frames search
        inner, uv, status, _ = self.eakf_stc.step_state(state.inner, grey)
        fused, outs, weights, statuses = [], [], [], []
        for i, f in enumerate(state.filters):
            ok = bool(status[i] != TrackStatus.LOST) and bool(torch.isfinite(uv[i]).all())
            x, w, fix, _ = f.step(frames[i], uv[i], ok)
            fused.append(x)
            outs.append(f.reported(x))
            weights.append(w if isinstance(w, Tensor) else x.new_tensor(w))
            statuses.append(f.verdict(TorchOps.value(outs[-1]), fix))
        out = torch.stack(outs)
        w = torch.stack(weights)
        hard = w.detach() > 0.5
        if bool(hard.any()):
            inner = self._reanchor(inner, grey, torch.stack(fused), w, hard)
        return AnchoredState(inner, state.filters, list(frames)), out, statuses

    def _reanchor(self, s: FusionState, grey: Tensor, uv: Tensor, w: Tensor, hard: Tensor
                  ) -> FusionState:
        """EAKFSTC.reanchor on the streams of ``hard`` with weights ``w`` (1 forward)."""
        d = (uv - s.kf.uv) * w[:, None]
        shift = torch.zeros_like(s.kf.x)
        shift[..., 0], shift[..., 2] = d, d
        kf = dataclasses.replace(s.kf, x=s.kf.x + shift)
        zshift = torch.zeros_like(s.kf.Z)
        zshift[..., 0] = d
        kf.Z = s.kf.Z + zshift
        if s.kf.x_post is not None:
            kf.x_post = s.kf.x_post + shift
        stc_mod = self.eakf_stc.stc
        learned = stc_mod.learn(s.stc, grey, torch.where(hard[:, None], uv, s.stc.pos),
                                w / stc_mod.rho)
        keep = hard.view(-1, *([1] * (learned.H_f.dim() - 1)))
        H_f = torch.where(keep, learned.H_f, s.stc.H_f)
        H_ref = (learned.H_ref if learned.H_ref is None or s.stc.H_ref is None
                 else torch.where(keep, learned.H_ref, s.stc.H_ref))
        stc = dataclasses.replace(learned, H_f=H_f, H_ref=H_ref)
        coast = torch.where(hard, torch.zeros_like(s.coast), s.coast)
        return dataclasses.replace(s, stc=stc, kf=kf, coast=coast,
                                   status=torch.where(hard, torch.zeros_like(s.status),
                                                      s.status))


# --------------------------------------------------------------------------- live loop

class AnchoredTracker(Tracker):
    """The live tracker on one stream (the live loop's): EAKF-STC's numpy twin
    (:class:`~torchseam.track.fusion.LiteEAKFSTC`) and :class:`AnchoredFilter` on numpy, with the
    fitted values of ``live`` (a :class:`AnchoredModel`: :func:`load_anchored_model` reads the
    shipped model file), its fixes found by ``tipm``.

    Example:
        >>> from torchseam.vision.tipm import load_tipm
        >>> trk = AnchoredTracker(load_anchored_model(), load_tipm())  # the shipped model
        >>> trk.init(frame0, uv0)             # doctest: +SKIP
        >>> res = trk.track(frame1)           # doctest: +SKIP
    """

    name = "anchored"

    def __init__(self, live: AnchoredModel, tipm: Tipm) -> None:
        self.live = live
        self.inner = LiteTracker(live.eakf_stc)
        self.fitted_fps = self.inner.fitted_fps
        self.cfg = live.cfg
        self.values = live.fusion.values()   # the fitted values the filter runs with
        self.filter = AnchoredFilter(self.cfg, tipm, self.values)
        self._expected: np.ndarray | None = None
        # driven by a loop that predicts the point (expect() called, even with None): each
        # frame's fused point is reported as it is; offline a jump's own frame reports the
        # prediction it left (AnchoredFilter.reported)
        self._predicted = False
        self._frame: np.ndarray | None = None
        self.glare = 0.0
        self.fix: Fix | None = None  # this frame's TIPM corner and what became of it
        self.arm_dirs: np.ndarray | None = None  # this frame's arm directions (clean fix)

    # the filter's state, for inspection (and for tests that place it)
    @property
    def x(self) -> np.ndarray | None:
        return self.filter.x

    @x.setter
    def x(self, value: np.ndarray | None) -> None:
        self.filter.x = value

    @property
    def P(self) -> np.ndarray | None:  # noqa: N802 - the math's name
        return self.filter.P

    @P.setter
    def P(self, value: np.ndarray | None) -> None:  # noqa: N802
        self.filter.P = value

    @property
    def Q(self) -> np.ndarray:  # noqa: N802
        return self.filter.Q

    @property
    def tipm(self) -> Tipm:
        return self.filter.tipm

    @tipm.setter
    def tipm(self, value: Tipm) -> None:
        self.filter.tipm = value

    @property
    def status(self) -> int:
        return self.filter.status

    @property
    def reacquired(self) -> int:
        return self.filter.reacquired

    def expect(self, uv: np.ndarray | None) -> None:
        """Where the feature point should be in the next frame, from the robot's motion (the
        live loop knows the camera's pose and the seam seen so far): it replaces the filter's
        random-walk prediction for that frame. None: no idea."""
        self._predicted = True
        self._expected = None if uv is None or not np.isfinite(uv).all() else np.asarray(
            uv, float)

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.inner.init(frame, uv)
        self.filter.start(np.asarray(uv, float))
        self._frame = None

    def idle(self) -> None:
        """Between frames: EAKF-STC's learning of the last update, and, while the track has no
        evidence, the whole-frame search (:meth:`AnchoredFilter.search`). Run here, after the
        frame's command is out, it costs the frame-to-point latency nothing."""
        self.inner.idle()
        frame, self._frame = self._frame, None
        self.filter.search(frame)

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        res = self.track(frame)
        return res.uv, res.status

    def track(self, frame: np.ndarray) -> TrackResult:
        """The point on ``frame`` and its status, decided by what the image shows there (see
        the module docstring); the filter's own confidence does not decide it."""
        expected, self._expected = self._expected, None  # for this frame only
        self._frame = frame
        uv, status = self.inner.update(frame)
        # EAKF-STC that gave up is no measurement; the filter goes on from its prediction and
        # a far corner is taken only through the persistence test of search()
        inner_ok = status != TrackStatus.LOST and bool(np.isfinite(uv).all())
        x, reanchor, fix, obs = self.filter.step(frame, uv, inner_ok, expected)
        if reanchor:
            self.inner.reanchor(frame, np.array(x, dtype=float))
        out = np.array(x if self._predicted else self.filter.reported(x), dtype=float)
        self.glare, self.fix = obs.glare, fix
        arm_dirs = (arm_directions(obs.res) if fix is not None and fix.taken
                    and obs.res is not None
                    and obs.res.inlier_rms_px <= self.values["max_rms_px"]
                    else None)
        self.arm_dirs = arm_dirs
        status = self.filter.verdict(out, fix)
        return TrackResult(out, status, fix, obs.stripe, arm_dirs, obs.glare)


def check_fitted_values(values: Mapping[str, float], where: str) -> None:
    """Every fitted value finite and positive (a file from a diverged fit is refused)."""
    for k, v in values.items():
        if not (math.isfinite(v) and v > 0):
            raise TorchseamError(f"{where}: fitted {k} = {v} is not a positive number")


def fitted_eakf_stc(model: dict | EAKFSTC | None = None,
                    model_path: str | Path | None = None) -> EAKFSTC:
    """EAKF-STC with fitted parameters: those of ``model_path`` (a model file, as
    ``torchseam train`` writes, live tracker or EAKF-STC alone; FitError naming it when it is
    missing or does not fit), else those of the shipped ``models/live_tracker.safetensors``
    (else the paper's defaults, with a warning). An explicit ``model`` configuration
    (TrackerConfig fields) is taken as given: the fitted file would silently overwrite the
    values asked for; a module already built is returned as it is."""
    if isinstance(model, EAKFSTC):
        return model
    if model and model_path is not None:
        raise TorchseamError("give a tracker configuration or a model file, not both")
    if model:
        return EAKFSTC(model)
    # the STC extensions are structural (their parameters exist only when switched on): build
    # the module the file was fitted as
    path = Path(model_path) if model_path is not None else model_file.DEFAULT_MODEL
    fitted = ((model_file.read_model(path)[1].get("tracker_config") or {})
              if model_path is not None or path.is_file() else {})
    module = EAKFSTC({k: fitted[k] for k in STRUCTURAL_STC if k in fitted})
    model_file.load_fitted(module, model_path)
    return module


def load_anchored_model(model_path: str | Path | None = None, cfg: AnchorConfig | None = None,
                      model: dict | None = None) -> AnchoredModel:
    """The live tracker with the fitted values of ``model_path`` (default: the shipped
    ``models/live_tracker.safetensors``). ``model``: an explicit EAKF-STC configuration
    (TrackerConfig fields) instead of a file; the fusion then keeps ``cfg``'s values (the
    starting values of a fit, ``configs/anchor.yaml``), as it does, with a warning, for a file
    of EAKF-STC alone or when no model file is present."""
    cfg = cfg if cfg is not None else load_anchor_config()
    live = AnchoredModel(fitted_eakf_stc(model, model_path), cfg)
    if model:
        return live
    path = Path(model_path) if model_path is not None else model_file.DEFAULT_MODEL
    if not path.is_file():
        return live  # fitted_eakf_stc warned
    if model_file.read_model(path)[1]["format"] != model_file.LIVE_FORMAT:
        log.warning("%s holds EAKF-STC alone: the fusion runs with its starting values "
                    "(configs/anchor.yaml), not fitted ones", path)
        return live
    model_file.load_fitted(live, path)
    check_fitted_values(live.fusion.values(), str(path))
    return live
