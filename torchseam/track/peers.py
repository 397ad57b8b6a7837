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

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from torchseam.core.dataset import check_frame
from torchseam.core.errors import TorchseamError
from torchseam.core.orient import FrameView
from torchseam.track import model_file
from torchseam.track.anchored import (
    AnchorConfig,
    AnchoredTracker,
    blind_status,
    fitted_eakf_stc,
    load_anchor_config,
    load_anchored_model,
    observe,
)
from torchseam.track.base import Fix, Tracker, TrackResult
from torchseam.track.fusion import LiteTracker, TrackStatus
from torchseam.track.names import TRACKERS
from torchseam.track.stc import STC
from torchseam.vision.tipm import (
    Tipm,
    find_view,
    red_response,
)

STATUS_NAMES = {int(s): s.name.lower() for s in TrackStatus}
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
    """TIPM (``tipm``) on every frame: no memory; a frame without a point is LOST (NaN)."""

    name = "tipm"

    def __init__(self, tipm: Tipm) -> None:
        self.tipm = tipm

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        pass

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        res = self.tipm(frame)
        return res.uv, int(TrackStatus.TRACKED if res.ok else TrackStatus.LOST)


class TorchTracker(Tracker):
    """Plain STC from :mod:`torchseam.track` (the batched torch module), one stream (B = 1);
    it never declares the track lost (the paper's STC has no such test)."""

    def __init__(self, name: str, module: STC) -> None:
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


class OpenCVTracker(Tracker):
    """KCF / CSRT / MOSSE following a box centred on the feature point."""

    def __init__(self, name: str) -> None:
        self.name = name
        # opencv-contrib's trackers: cv2's stubs do not list them
        makers: dict[str, Callable[[], Any]] = {
            "kcf": cv2.TrackerKCF_create,  # type: ignore[attr-defined]
            "csrt": cv2.TrackerCSRT_create,  # type: ignore[attr-defined]
            "mosse": cv2.legacy.TrackerMOSSE_create}  # type: ignore[attr-defined]
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


class Confirmed(Tracker):
    """A tracker whose own status is no image evidence, held to the status every tracker
    gives (:class:`~torchseam.track.base.TrackResult`): STC, KCF, CSRT and MOSSE say
    ``tracked`` whenever they give a point, EAKF-STC whenever it trusts its filter, however
    far the point has drifted off the stripe's corner. Here a frame is ``tracked`` only when
    TIPM's corner in the window round the tracker's point is seen (both arms reach it) and
    lies within ``evidence_px`` of it, as for the live tracker; ``coasting`` otherwise and
    ``lost`` by the live tracker's rule (:func:`~torchseam.track.anchored.blind_status`; the
    settings of ``configs/anchor.yaml``). The point is the tracker's own: the corner is
    weighed as evidence (``TrackResult.fix``, never taken), not used to correct it.

    Example:
        >>> from torchseam.vision.tipm import load_tipm
        >>> trk = Confirmed(OpenCVTracker("mosse"), load_tipm(), load_anchor_config())
        >>> trk.init(frame0, uv0)               # doctest: +SKIP
        >>> trk.track(frame1).tracked           # doctest: +SKIP
    """

    def __init__(self, inner: Tracker, tipm: Tipm, cfg: AnchorConfig) -> None:
        self.inner, self.tipm, self.cfg = inner, tipm, cfg
        self.name, self.fitted_fps = inner.name, inner.fitted_fps
        self.coast = 0                                 # frames without evidence in a row
        self.last_evidence: np.ndarray | None = None   # the last point with evidence

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.inner.init(frame, uv)
        self.coast, self.last_evidence = 0, np.asarray(uv, float).copy()

    def expect(self, uv: np.ndarray | None) -> None:
        self.inner.expect(uv)

    def idle(self) -> None:
        self.inner.idle()

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        res = self.track(frame)
        return res.uv, res.status

    def track(self, frame: np.ndarray) -> TrackResult:
        uv, status = self.inner.update(frame)
        uv = np.asarray(uv, float)
        if status == TrackStatus.LOST or not np.all(np.isfinite(uv)):
            self.coast += 1
            return TrackResult(uv, int(TrackStatus.LOST))
        obs = observe(self.tipm, frame, uv, None, self.cfg, shallow=False)
        fix = None
        if obs.res is not None and obs.z is not None and obs.shape_cov is not None:
            rms = obs.res.inlier_rms_px
            fix = Fix(obs.z.copy(), rms * rms * obs.shape_cov, 1.0, taken=False, seen=obs.seen)
        if fix is not None and fix.seen and float(
                np.linalg.norm(fix.uv - uv)) <= self.cfg.evidence_px:
            self.coast, self.last_evidence = 0, uv.copy()
            status = int(TrackStatus.TRACKED)
        else:
            self.coast += 1
            status = blind_status(self.cfg, self.coast, uv, self.last_evidence)
        return TrackResult(uv, status, fix, obs.stripe, None, obs.glare)


def make_tracker(name: str, tipm: Tipm, model: dict | None = None,
                 model_path: str | Path | None = None) -> FrameTracker:
    """A tracker by CLI name (see ``TRACKERS``); ``tipm`` is the TIPM of those that run it
    (``tipm`` on every frame, ``anchored`` for its fixes). The EAKF-STC trackers read their
    fitted model: ``model_path`` (a model file; ``eakf-stc`` takes the EAKF-STC part of a
    live-tracker file), else ``anchored`` ``models/live_tracker.safetensors`` (with
    ``configs/anchor.yaml``, see :func:`~torchseam.track.anchored.load_anchored_model`) and
    ``eakf-stc`` its own fit ``models/eakf_stc.safetensors``, unless ``model`` (a TrackerConfig
    mapping) is given. A ``model_path`` for a tracker without EAKF-STC is an error (it would be
    ignored). The trackers whose status is no image evidence (all but ``anchored`` and
    ``tipm``) are :class:`Confirmed`: ``tracked`` means what it means for every tracker."""
    if model_path is not None and name not in ("eakf-stc", "anchored"):
        raise TorchseamError(f"--model {model_path}: tracker {name} loads no model (only "
                             "eakf-stc and anchored do)")
    if name == "anchored":
        return AnchoredTracker(load_anchored_model(model_path, model=model), tipm)
    if name == "tipm":
        return TipmPerFrame(tipm)
    inner: Tracker
    if name == "eakf-stc":
        if model_path is None and not model and model_file.EAKF_STC_MODEL.is_file():
            model_path = model_file.EAKF_STC_MODEL  # its own fit, not the live tracker's part
        inner = LiteTracker(fitted_eakf_stc(model, model_path))
    elif name == "stc":
        inner = TorchTracker(name, STC())
    elif name in ("kcf", "csrt", "mosse"):
        inner = OpenCVTracker(name)
    else:
        raise TorchseamError(f"unknown tracker {name!r}: use one of {', '.join(TRACKERS)}")
    return Confirmed(inner, tipm, load_anchor_config())


def run_tracker(tracker: FrameTracker, frames, uv0: np.ndarray | None, tipm: Tipm,
                progress: Callable[[int], None] | None = None, axis: str = "rows",
                response: str = "red"
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """Track an iterable of frames (colour or mono), the way the live loop drives a tracker:
    ``update`` on each frame, then its ``idle()`` (the learning for the next frame, e.g.
    EAKF-STC's context model), when it has one, before the next frame arrives.

    Args:
        uv0: start point on frame 0 (camera pixels); None: TIPM on frame 0 (it must find the
            stripe there).
        tipm: that TIPM, also the one that finds the view with ``auto``.
        axis: how the stripe runs: ``rows``, ``columns`` (the tracker sees each frame turned,
            see :mod:`torchseam.core.orient`) or ``auto`` (found on frame 0).
        response: a colour frame's stripe response: ``red`` (red excess), ``intensity`` (the
            channels' mean) or ``auto`` (found on frame 0, see :func:`find_view`).

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
