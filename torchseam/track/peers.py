"""One interface over every tracker the CLI and the benchmarks compare.

``FrameTracker`` (:class:`~torchseam.track.base.Tracker`): ``init(frame, uv)`` on the first
frame, then ``track(frame) -> TrackResult`` (or ``update(frame) -> (uv, status)``) per frame,
colour or mono. Peers: TIPM on every frame, plain STC, EAKF-STC (the fitted module's numpy
twin, B = 1), ``anchored`` (EAKF-STC and TIPM fused by a Kalman filter on the point,
EAKF-STC re-anchored on TIPM's fixes: the live loop's default, see
:class:`AnchoredTracker`), and OpenCV's KCF, CSRT and MOSSE (a box around the feature
point; the point keeps its offset in the box).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from torchseam.core.config import CONFIG_DIR, config_field, load_config
from torchseam.core.dataset import check_frame
from torchseam.core.errors import TorchseamError
from torchseam.core.orient import FrameView
from torchseam.track.base import Fix, Tracker, TrackResult
from torchseam.track.fusion import EAKFSTC, TrackStatus
from torchseam.track.lite import LiteEAKFSTC
from torchseam.track.stc import STC
from torchseam.vision.tipm import (
    Tipm,
    TipmResult,
    arm_shape,
    find_view,
    power_sums,
    quad_normal_adjugate,
    red_response,
)

TRACKERS = ("eakf-stc", "anchored", "stc", "tipm", "kcf", "csrt", "mosse")
STATUS_NAMES = {int(s): s.name.lower() for s in TrackStatus}
#: TrackerConfig fields that add parameters to the module: read from the model file
STRUCTURAL_STC = ("reg", "anchor", "anchor_frames")
OPENCV_BOX_PX = 64  # side of the box the OpenCV trackers follow (twice the target, like STC)


#: what the live loop and the CLI drive (see :class:`~torchseam.track.base.Tracker`)
FrameTracker = Tracker


def grey_tensor(frame: np.ndarray, planes: list[np.ndarray] | None = None) -> torch.Tensor:
    """(1, H, W) uint8 tensor of the red-stripe response the torch trackers see (they convert
    only the context windows they crop to float, not the whole frame). ``planes``: three
    reusable (H, W) uint8 buffers (see :func:`red_response`); the tensor then shares the first
    and is valid until they are reused."""
    return torch.from_numpy(red_response(frame, out=planes)).unsqueeze(0)


class TipmPerFrame(Tracker):
    """TIPM on every frame: no memory; a frame without a point is LOST (NaN)."""

    name = "tipm"

    def __init__(self) -> None:
        self.tipm = Tipm()

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        pass

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        res = self.tipm(frame)
        return res.uv, int(TrackStatus.TRACKED if res.ok else TrackStatus.LOST)


class TorchTracker(Tracker):
    """Plain STC from :mod:`torchseam.track` (the batched torch module), one stream (B = 1);
    it never declares the track lost (the paper's STC has no such test)."""

    def __init__(self, name: str, module: torch.nn.Module) -> None:
        self.name = name
        self.module = module.eval()
        self._planes: list[np.ndarray] = []  # reused per frame: the modules keep no frame

    def _grey(self, frame: np.ndarray) -> torch.Tensor:
        if not self._planes or self._planes[0].shape != frame.shape[:2]:
            self._planes = [np.empty(frame.shape[:2], np.uint8) for _ in range(3)]
        return grey_tensor(frame, self._planes)

    @torch.inference_mode()
    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.module.init(self._grey(frame), torch.tensor(np.asarray(uv)[None],
                                                           dtype=torch.float32))

    @torch.inference_mode()
    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        uv, _ = self.module.step(self._grey(frame))
        return uv[0].numpy().astype(float), int(TrackStatus.TRACKED)  # STC has no status


class LiteTracker(Tracker):
    """EAKF-STC for one stream: the fitted module's parameters run by its numpy twin
    :class:`~torchseam.track.lite.LiteEAKFSTC` (same equations, a third of the time at B = 1,
    where the module's tensor-op dispatch dominates)."""

    name = "eakf-stc"

    def __init__(self, module: EAKFSTC) -> None:
        self.lite = LiteEAKFSTC.from_module(module)

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


class OpenCVTracker(Tracker):
    """KCF / CSRT / MOSSE following a box centred on the feature point."""

    def __init__(self, name: str) -> None:
        self.name = name
        makers: dict[str, Callable[[], object]] = {
            "kcf": cv2.TrackerKCF_create, "csrt": cv2.TrackerCSRT_create,
            "mosse": cv2.legacy.TrackerMOSSE_create}
        self._make = makers[name]
        self.offset = np.zeros(2)
        self.last = np.full(2, np.nan)

    @staticmethod
    def _bgr(frame: np.ndarray) -> np.ndarray:
        """OpenCV's trackers take colour frames: a mono frame is given as grey BGR."""
        return cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        frame = self._bgr(frame)
        self.tracker = self._make()
        h = OPENCV_BOX_PX // 2
        box = (int(round(uv[0])) - h, int(round(uv[1])) - h, OPENCV_BOX_PX, OPENCV_BOX_PX)
        self.offset = np.asarray(uv, float) - np.array([box[0] + h, box[1] + h])
        self.tracker.init(frame, box)
        self.last = np.asarray(uv, float)

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        ok, box = self.tracker.update(self._bgr(frame))
        if not ok:
            return self.last, int(TrackStatus.LOST)
        x, y, w, h = box
        self.last = np.array([x + w / 2, y + h / 2]) + self.offset
        return self.last, int(TrackStatus.TRACKED)


@dataclass(frozen=True)
class AnchorConfig:
    """Settings of :class:`AnchoredTracker` (``configs/anchor.yaml``; px unless named)."""

    window_px: int = config_field(lo=16)
    reanchor_px: float = config_field(lo=0.0)
    motion_u_px: float = config_field(lo=0.0, lo_open=True)
    motion_v_px: float = config_field(lo=0.0, lo_open=True)
    track_u_px: float = config_field(lo=0.0, lo_open=True)
    track_v_px: float = config_field(lo=0.0, lo_open=True)
    fix_noise: float = config_field(lo=0.0, lo_open=True)
    fix_floor_px: float = config_field(lo=0.0, lo_open=True)
    fix_gate: float = config_field(lo=0.0, lo_open=True)
    track_gate: float = config_field(lo=0.0, lo_open=True)
    max_rms_px: float = config_field(lo=0.0, lo_open=True)
    arm_noise_px: float = config_field(lo=0.0, lo_open=True)
    slope_step: float = config_field(lo=0.0, lo_open=True)
    curvature_step: float = config_field(lo=0.0, lo_open=True)
    glare_px: int = config_field(lo=1)
    glare_start: float = config_field(lo=0.0)
    glare_scale: float = config_field(lo=0.0, lo_open=True)
    evidence_px: float = config_field(lo=0.0, lo_open=True)
    lost_frames: int = config_field(lo=1)
    lost_px: float = config_field(lo=0.0, lo_open=True)
    reacquire_frames: int = config_field(lo=1)
    reacquire_step_px: float = config_field(lo=0.0, lo_open=True)
    support_px: float = config_field(lo=0.0, lo_open=True)
    support_points: int = config_field(lo=1)


def load_anchor_config(path: str | Path | None = None) -> AnchorConfig:
    return load_config(AnchorConfig, path or CONFIG_DIR / "anchor.yaml")


def corner_cov(res: TipmResult, noise: float, floor_px: float,
               prior: np.ndarray | None = None,
               arm_cols: tuple[float, float] = (5.0, 120.0)) -> np.ndarray:
    """(2, 2) covariance of a TIPM corner: each arm line is off along its normal by
    ``noise * max(rms, floor_px)``; where the lines meet at a shallow angle the corner is weak
    along the stripe (mostly u) and firm across it.

    An arm whose centre-line points stop short of the corner (spatter across it, a dropout, a
    gap) is extrapolated to it: its variance there is scaled by its fit's leverage at the
    corner over a complete arm's (one point per column from ``arm_cols[0]`` to
    ``arm_cols[1]`` px from the corner: TIPM's ``corner_gap_px`` and ``fit_window_px``;
    ``prior``: the arm prior the fit used, see :meth:`Tipm.corner`), never below 1. Measured
    on heavy-arc rings (seeds 0 and 2, 3 723 fixes): without it the fixes with an
    extrapolated arm (leverage ratio > 2) had Mahalanobis^2 errors of mean 26-31 (2 expected)
    and gave 31 of the 57 fixes > 2 px off; with it the errors are chi^2(2)-like (mean 1.8,
    99th percentile 9.3).
    """
    assert res.arms is not None and res.centre is not None
    xc = float(res.uv[0] - res.u0)
    normals = np.array([[-(a[1] + 2 * a[2] * xc), 1.0] for a in res.arms])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    sigma = noise * max(res.rms_px, floor_px)
    gap, window = arm_cols
    u = res.centre[:, 0] - res.u0  # sorted by u (TIPM's centre line is)
    cut = np.searchsorted(u, (-window, -gap, gap, window), side="left")
    cut[1] = np.searchsorted(u, -gap, side="right")
    cut[3] = np.searchsorted(u, window, side="right")
    full = _full_arm_sums(float(gap), float(window))
    var = np.empty(2)
    for side in range(2):
        x = u[cut[2 * side]:cut[2 * side + 1]]
        w = (0.0, 0.0) if prior is None else (float(prior[side, 2]), float(prior[side, 3]))
        # (fewer than 3 points: TIPM gives no corner then; if it did, the arm says ~nothing)
        ratio = (_leverage(power_sums(x), xc, w) / _leverage(full[side], xc, w)
                 if len(x) >= 3 else 1e6)
        var[side] = sigma * sigma * max(1.0, ratio)
    n_inv = _inv2(normals)
    return (n_inv * var) @ n_inv.T


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
    red = red_response(np.ascontiguousarray(box)).ravel()
    return float(np.partition(red, len(red) // 2)[len(red) // 2])  # half of np.median's cost


def arm_directions(res: TipmResult) -> np.ndarray:
    """(2, 2) unit image directions (du, dv) of the left and the right arm leaving a found
    corner: the tangents of TIPM's arm fits where they meet.

    Fitted to every centre-line column of an arm, they hold the arm's direction at the corner
    2-3x tighter than ECAL's few circle crossings, and without ECAL's bias from a feature point
    off the arm (ECAL measures angles around that point; measured per frame against the true
    surfaces on heavy-arc rings, main-pipe arm: std 0.3-0.5 vs 0.8-1.2 degrees).

    Example:
        >>> d = arm_directions(Tipm()(frame))  # doctest: +SKIP
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
    ``sums`` (:func:`~torchseam.vision.tipm.power_sums`), ridge weights ``w`` on slope and
    curvature (as :func:`~torchseam.vision.tipm._quadfit`): ``e^T A^-1 e`` with
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
        >>> r = Tipm().corner(np.stack([np.arange(0.0, 200), 100 - np.abs(np.arange(0.0, 200)
        ...                             - 100) * 0.5], axis=1))
        >>> corner_seen(r, 10.0, 5)
        True
    """
    if res.centre is None or not len(res.centre):
        return False
    d = res.centre[:, 0] - res.uv[0]
    return bool(np.sum((d < 0) & (d >= -support_px)) >= points
                and np.sum((d > 0) & (d <= support_px)) >= points)


class AnchoredTracker(Tracker):
    """EAKF-STC with TIPM as an absolute anchor, fused by a small Kalman filter on the point.

    Per frame: EAKF-STC tracks; TIPM looks for the stripe corner in a window around the
    filter's prediction, its arm fits pulled toward the arm shape of the last fix taken (slope
    at the corner and curvature change little per frame: :func:`~torchseam.vision.tipm.arm_shape`,
    the prior's variance grows by ``slope_step^2``, ``curvature_step^2`` per frame since); a
    random-walk filter on (u, v) then takes the TIPM fix with an anisotropic covariance
    (:func:`corner_cov`) and the EAKF-STC point as a coarse measurement, each through a
    Mahalanobis gate. When a fix was taken and EAKF-STC is more than ``reanchor_px`` off, it is
    moved onto the filtered point (:meth:`EAKFSTC.reanchor`).
    A clean fix (arm-fit RMS <= ``max_rms_px``) outside the gate restarts the filter there: in
    closed loop the image jumps 5-10 px when the torch turns to a new target, and EAKF-STC can
    run away under arc light, dragging the filter with it; loose fixes outside the gate are
    refused. When EAKF-STC declares the track lost it stops being a measurement (the filter
    coasts on its prediction) and is moved onto the next fix taken; a corner far from the
    track is taken only through the persistence test of :meth:`idle`.
    Under red glare around the predicted point (:func:`glare_level` above ``glare_start``) both
    measurements are trusted less: their covariances are multiplied by
    ``1 + ((glare - glare_start) / glare_scale)^2``, so the filter leans on its prediction
    while the glare lasts. Both, because both go wrong together there and the same way: on a
    glare band across the corner TIPM's fits stay tight while the corner slides along the
    stripe, and EAKF-STC, re-anchored onto it, follows. Measured over 4 602 fixes on 16 heavy
    sequences (``bench/fix_calibration.py``, TIPM's centre line refined around each column's
    centroid): Mahalanobis^2 errors of mean 1.1 at glare below 60 grey levels (2 expected),
    2.9 at 60-80, 8.5 at 80-100; 1.1-1.9 with the term. (Before that refinement a stripe
    saturated on glare left the centre line on one of its two ridges and the corner slid
    3-4 px: 5.5 and 11.5 in those bins.)
    Why (measured on 30 simulated heavy sequences, seeds 1000-1029): a free quadratic on an arm
    with a gap next to the corner slides the corner 4-15 px along the shallow stripe with a
    tight fit, which no residual test catches; the arm prior cuts those fixes > 3 px from 126
    to 15 of 5 650. EAKF-STC one frame after a good fix is worse than holding the fix (RMSE
    1.05 vs 0.78 px: the true point is a random walk, 0.5 px/frame in u, 0.3 in v), so the
    filter outputs the fix or the hold, and uses EAKF-STC only as a weak pull.

    Example:
        >>> trk = AnchoredTracker()           # configs/anchor.yaml, fitted EAKF-STC
        >>> trk.init(frame0, uv0)             # doctest: +SKIP
        >>> uv, status = trk.update(frame1)   # doctest: +SKIP
    """

    name = "anchored"

    def __init__(self, model: dict | None = None, cfg: AnchorConfig | None = None) -> None:
        self.inner = LiteTracker(fitted_eakf_stc(model))
        self.tipm = Tipm()
        self.cfg = cfg or load_anchor_config()
        c = self.cfg
        self.Q = np.diag([c.motion_u_px ** 2, c.motion_v_px ** 2])
        self.R_track = np.diag([c.track_u_px ** 2, c.track_v_px ** 2])
        self.x: np.ndarray | None = None       # filtered point (u, v)
        self.P = np.eye(2)
        self.shape: np.ndarray | None = None   # arm_shape of the last fix taken
        self.age = 0                           # frames since that fix
        # this frame's TIPM window: (stripe response, stripe mask, (x0, y0) of the window) or None;
        # valid until the next update (the arrays are TIPM's reused planes)
        self.stripe: tuple[np.ndarray, np.ndarray, tuple[int, int]] | None = None
        # this frame's arm directions at the corner from the TIPM fix taken when it is clean
        # (arm-fit RMS <= max_rms_px), (2, 2) unit image vectors (left, right arm), or None
        self.arm_dirs: np.ndarray | None = None
        self._expected: np.ndarray | None = None  # the next frame's pixel from the robot's motion
        self.glare = 0.0  # this frame's glare_level around the predicted point (grey levels)
        self.fix: Fix | None = None  # this frame's TIPM corner and what became of it, or None
        # status from image evidence (see update): frames without it in a row, and where the
        # last evidence was
        self.coast = 0
        self.last_evidence: np.ndarray | None = None
        self.status = int(TrackStatus.TRACKED)
        # re-acquisition (see idle): this frame (until idle), the whole-frame corners found in
        # a row while the track had no evidence, and the corner to move to on the next frame
        self._frame: np.ndarray | None = None
        self._found: list[np.ndarray] = []
        self._reacquire: np.ndarray | None = None
        self.reacquired = 0  # times the track was moved onto persistent independent corners

    def expect(self, uv: np.ndarray | None) -> None:
        """Where the feature point should be in the next frame, from the robot's motion (the
        live loop knows the camera's pose and the seam seen so far): it replaces the filter's
        random-walk prediction for that frame. In closed loop the image jumps 5-10 px when the
        torch turns to a new target, which a random walk cannot follow. None: no idea."""
        self._expected = None if uv is None or not np.all(np.isfinite(uv)) else np.asarray(
            uv, float)

    def _restart(self, uv: np.ndarray, P: np.ndarray, shape: np.ndarray | None) -> None:
        self.x, self.P = np.asarray(uv, float).copy(), P
        self.shape, self.age = shape, 0

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.inner.init(frame, uv)
        self._restart(uv, self.Q.copy(), None)
        self.coast, self.last_evidence = 0, np.asarray(uv, float).copy()
        self.status = int(TrackStatus.TRACKED)
        self._frame, self._found, self._reacquire = None, [], None

    def idle(self) -> None:
        """Between frames: EAKF-STC's learning of the last update, and, while the track has no
        evidence, the search that keeps a wrong track from lasting.

        No gate may hold a wrong track forever: the filter's gates refuse fixes far from its
        prediction, and the arm prior pulls the windowed fits toward the shape it last saw.
        So on a frame without evidence TIPM looks at the whole frame, without the prior:
        when ``reacquire_frames`` such corners in a row each lie within
        ``reacquire_step_px`` of the one before (a corner that persists, not spatter) and away
        from the track, the next update starts again there. Run here, after the frame's
        command is out, it costs the frame-to-point latency nothing.
        """
        self.inner.idle()
        frame, self._frame = self._frame, None
        if frame is None or self.status == TrackStatus.TRACKED:
            self._found.clear()
            return
        c = self.cfg
        res = self.tipm(frame)
        if (not res.ok or not corner_seen(res, c.support_px, c.support_points)
                or (self.x is not None and np.linalg.norm(res.uv - self.x) <= c.evidence_px)):
            self._found.clear()
            return
        if self._found and np.linalg.norm(res.uv - self._found[-1]) > c.reacquire_step_px:
            self._found.clear()
        self._found.append(res.uv)
        if len(self._found) >= c.reacquire_frames:
            self._reacquire, self._found = res.uv, []

    def _prior(self) -> np.ndarray | None:
        if self.shape is None:
            return None
        c = self.cfg
        n = max(self.age, 1)  # random walk of the arm shape since the last fix
        out = np.empty((2, 4))
        out[:, :2] = self.shape
        out[:, 2] = c.arm_noise_px ** 2 / (n * c.slope_step ** 2)
        out[:, 3] = c.arm_noise_px ** 2 / (n * c.curvature_step ** 2)
        return out

    def _measure(self, z: np.ndarray, R: np.ndarray, gate: float) -> bool:
        """Kalman update with ``z`` (covariance ``R``) unless its Mahalanobis distance from
        the filtered point exceeds ``gate``."""
        y = z - self.x
        S_inv = _inv2(self.P + R)
        if y @ S_inv @ y > gate * gate:
            return False
        K = self.P @ S_inv
        self.x = self.x + K @ y
        self.P = (np.eye(2) - K) @ self.P
        return True

    def _fix(self, anchor: np.ndarray, res: TipmResult, inflate: float = 1.0) -> bool:
        """Take or refuse a TIPM fix (its covariance times ``inflate``); True when the filter
        moved onto it."""
        c = self.cfg
        # the prior the fit used: shape and age are those of the last fix taken until below
        t = self.tipm.cfg
        cov = corner_cov(res, c.fix_noise, c.fix_floor_px, self._prior(),
                         (t.corner_gap_px, t.fit_window_px))
        R = inflate * cov
        taken = self._measure(anchor, R, c.fix_gate)
        if not taken and res.rms_px <= c.max_rms_px:
            # a clean corner the motion model did not expect: the image jumped (in closed loop
            # the camera turns with the torch at each new target, 5-10 px in one frame); a
            # clean fit is worth more than the random-walk prediction, so start again there
            self._restart(anchor, R, None)
            taken = True
        if taken:
            self.shape, self.age = arm_shape(res), 0
        self.fix = Fix(np.asarray(anchor, float).copy(), cov, inflate, taken,
                       corner_seen(res, c.support_px, c.support_points))
        return taken

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        res = self.track(frame)
        return res.uv, res.status

    def track(self, frame: np.ndarray) -> TrackResult:
        """The point on ``frame`` and its status, decided by what the image shows there:
        ``TRACKED`` only when this frame's TIPM corner (the stripe bends: two arms meet) lies
        within ``evidence_px`` of the point; ``COASTING`` when the point is predicted (no
        corner, or one that contradicts the track); ``LOST`` after ``lost_frames`` frames in a
        row without evidence, or once the prediction has moved ``lost_px`` from the last
        evidence. The filter's own confidence does not decide it."""
        self.stripe = self.arm_dirs = self.fix = None
        expected, self._expected = self._expected, None  # for this frame only
        self._frame = frame  # for idle()'s search (valid until then)
        uv, status = self.inner.update(frame)
        # EAKF-STC that gave up is no measurement; the filter goes on from its prediction,
        # the window below looks around it, and a far corner is taken only through the
        # persistence test of idle() (one whole-frame corner is not enough: glare edges and
        # spatter make corners too)
        inner_ok = status != TrackStatus.LOST and bool(np.all(np.isfinite(uv)))
        if self.x is None:
            self._restart(uv, self.Q.copy(), None)
        if self._reacquire is not None:
            # a corner the whole-frame search found persistently away from the track
            # (see idle): start again there; the window below looks for it on this frame
            self._restart(self._reacquire, self.Q.copy(), None)
            self._reacquire, expected = None, None
            self.reacquired += 1
        cfg = self.cfg
        self.age += 1
        self.P = self.P + self.Q
        if expected is not None:
            self.x = expected
        h, w = frame.shape[:2]
        cu, cv = self.x  # the filter's prediction: EAKF-STC can be the one that ran off
        self.glare = glare_level(frame, self.x, cfg.glare_px)
        inflate = 1.0 + (max(self.glare - cfg.glare_start, 0.0) / cfg.glare_scale) ** 2
        x0 = int(np.clip(cu - cfg.window_px, 0, w - 1))
        y0 = int(np.clip(cv - cfg.window_px, 0, h - 1))
        roi = np.ascontiguousarray(frame[y0:int(cv) + cfg.window_px + 1,
                                         x0:int(cu) + cfg.window_px + 1])
        taken = False
        if roi.shape[0] >= 16 and roi.shape[1] >= 16:
            # TIPM's stages by hand (the frame is checked already) to keep the stripe response
            # and mask of the window: ECAL reads them next (see ``stripe``)
            red, mask, why = self.tipm.stripe_mask(roi)
            self.stripe = (red, mask, (x0, y0))
            if not why:
                res = self.tipm.corner(self.tipm.centre(red, mask), mask, self._prior())
                if res.ok:
                    taken = self._fix(res.uv + (x0, y0), res, inflate)
                    if taken and res.rms_px <= cfg.max_rms_px:
                        # clean arms only: a fit over an arm cut short (glare, the other pipe)
                        # leaves the line, and its tangent turns (3-4 degrees seen)
                        self.arm_dirs = arm_directions(res)
        if inner_ok:
            self._measure(uv, inflate * self.R_track, cfg.track_gate)
        out = self.x.copy()
        if taken and (not inner_ok or np.linalg.norm(out - uv) > cfg.reanchor_px):
            self.inner.reanchor(frame, out)
        evidence = self.fix is not None and self.fix.seen and float(
            np.linalg.norm(self.fix.uv - out)) <= cfg.evidence_px
        return self._verdict(out, evidence)

    def _verdict(self, out: np.ndarray, evidence: bool) -> TrackResult:
        """The result of a frame with or without evidence at ``out`` (see track)."""
        c = self.cfg
        if evidence:
            self.coast, self.last_evidence = 0, np.asarray(out, float).copy()
            self.status = int(TrackStatus.TRACKED)
        else:
            self.coast += 1
            far = (self.last_evidence is None or not np.all(np.isfinite(out))
                   or float(np.linalg.norm(out - self.last_evidence)) > c.lost_px)
            self.status = int(TrackStatus.LOST if far or self.coast > c.lost_frames
                              else TrackStatus.COASTING)
        return TrackResult(np.asarray(out, float), self.status, self.fix, self.stripe,
                           self.arm_dirs, self.glare)


def fitted_eakf_stc(model: dict | EAKFSTC | None = None,
                    model_path: str | Path | None = None) -> EAKFSTC:
    """EAKF-STC with fitted parameters: those of ``model_path`` (an EAKF-STC model file, as
    ``torchseam train`` writes; FitError naming it when it is missing or does not fit), else
    those of ``models/eakf_stc.safetensors`` when present (else the paper's defaults, with a
    warning). An explicit ``model`` configuration (TrackerConfig fields) is taken as given: the
    fitted file would silently overwrite the values asked for; a module already built is
    returned as it is."""
    if isinstance(model, EAKFSTC):
        return model
    if model and model_path is not None:
        raise TorchseamError("give a tracker configuration or a model file, not both")
    if model:
        return EAKFSTC(model)
    from torchseam.fit import model_io  # the fitting stage owns the model file

    # the STC extensions are structural (their parameters exist only when switched on): build
    # the module the file was fitted as
    path = Path(model_path) if model_path is not None else model_io.DEFAULT_MODEL
    fitted = ((model_io.read_model(path)[1].get("tracker_config") or {})
              if model_path is not None or path.is_file() else {})
    module = EAKFSTC({k: fitted[k] for k in STRUCTURAL_STC if k in fitted})
    model_io.load_fitted(module, model_path)
    return module


def make_tracker(name: str, model: dict | None = None,
                 model_path: str | Path | None = None) -> FrameTracker:
    """A tracker by CLI name (see ``TRACKERS``). The EAKF-STC trackers load ``model_path``
    (an EAKF-STC model file), else ``models/eakf_stc.safetensors``, unless ``model`` (a
    TrackerConfig mapping) is given. A ``model_path`` for a tracker without EAKF-STC is an
    error (it would be ignored)."""
    if model_path is not None and name not in ("eakf-stc", "anchored"):
        raise TorchseamError(f"--model {model_path}: tracker {name} loads no model (only "
                             "eakf-stc and anchored do)")
    if name == "eakf-stc":
        return LiteTracker(fitted_eakf_stc(model, model_path))
    if name == "anchored":
        # the module is built here, so that the model file given is the one it holds
        return AnchoredTracker(fitted_eakf_stc(model, model_path) if model_path is not None
                               else model)
    if name == "stc":
        return TorchTracker(name, STC())
    if name == "tipm":
        return TipmPerFrame()
    if name in ("kcf", "csrt", "mosse"):
        return OpenCVTracker(name)
    raise TorchseamError(f"unknown tracker {name!r}: use one of {', '.join(TRACKERS)}")


def run_tracker(tracker: FrameTracker, frames, uv0: np.ndarray | None,
                progress: Callable[[int], None] | None = None, axis: str = "rows",
                response: str = "red"
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """Track an iterable of frames (colour or mono), the way the live loop drives a tracker:
    ``update`` on each frame, then its ``idle()`` (the learning for the next frame, e.g.
    EAKF-STC's context model), when it has one, before the next frame arrives.

    Args:
        uv0: start point on frame 0 (camera pixels); None: TIPM on frame 0 (it must find the
            stripe there).
        axis: how the stripe runs: ``rows``, ``columns`` (the tracker sees each frame turned,
            see :mod:`torchseam.core.orient`) or ``auto`` (found on frame 0).
        response: a colour frame's stripe response: ``red`` (red excess), ``intensity`` (the
            red channel) or ``auto`` (found on frame 0, see :func:`find_view`).

    Returns:
        ``(uv (N, 2), status (N,), seconds (N,), idle_seconds (N,), init_note)``: points in
        camera pixels, ``seconds`` from frame to point (``update``, the turn included),
        ``idle_seconds`` the work after it, between frames (0 for trackers without ``idle``);
        frame 0 is the start point.
    """
    it = iter(frames)
    try:
        first = next(it)
    except StopIteration:
        raise TorchseamError("no frames to track") from None
    tipm = Tipm()
    first = check_frame(first, name="frame 0")
    if "auto" in (axis, response):
        found = find_view(first, tipm, axis, response)
        if found is None:
            raise TorchseamError(f"frame 0: no stripe corner (stripe axis {axis}, response "
                                 f"{response}); give --stripe-axis and --stripe-response")
        view = found
    else:
        view = FrameView(axis, first.shape[0], response)
    note = "given"
    first = view.frame(first)
    if uv0 is None:
        res = tipm(first)
        if not res.ok:
            raise TorchseamError(f"frame 0: TIPM cannot start the tracker ({res.reason}); "
                                 "give the start point with --init U,V")
        uv0, note = view.to_camera(res.uv), "TIPM on frame 0"
    tracker.init(first, view.to_canonical(np.asarray(uv0, float)))
    uvs, stats, secs = [np.asarray(uv0, float)], [int(TrackStatus.TRACKED)], [0.0]
    idle_secs = [0.0]
    for k, frame in enumerate(it, start=1):
        t0 = time.perf_counter()
        uv, st = tracker.update(view.frame(check_frame(frame, name=f"frame {k}")))
        uv = view.to_camera(uv)
        t1 = time.perf_counter()
        tracker.idle()
        idle_secs.append(time.perf_counter() - t1)
        secs.append(t1 - t0)
        uvs.append(np.asarray(uv, float))
        stats.append(st)
        if progress:
            progress(k)
    return np.stack(uvs), np.array(stats), np.array(secs), np.array(idle_secs), note
