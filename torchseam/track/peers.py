"""One interface over every tracker the CLI and the benchmarks compare.

``FrameTracker``: ``init(frame, uv)`` on the first frame, then ``update(frame) -> (uv, status)``
per BGR frame. Peers: TIPM on every frame, plain STC, EAKF-STC (the torch modules, B = 1),
``anchored`` (EAKF-STC re-anchored by TIPM whenever TIPM finds a clean corner next to it: the
live loop's default, see :class:`AnchoredTracker`), and OpenCV's KCF, CSRT and MOSSE (a box
around the feature point; the point keeps its offset in the box).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
import torch

from torchseam.core.config import CONFIG_DIR, config_field, load_config
from torchseam.core.errors import TorchseamError
from torchseam.track.fusion import EAKFSTC, TrackStatus
from torchseam.track.stc import STC
from torchseam.vision.tipm import Tipm, red_response

TRACKERS = ("eakf-stc", "anchored", "stc", "tipm", "kcf", "csrt", "mosse")
STATUS_NAMES = {int(s): s.name.lower() for s in TrackStatus}
OPENCV_BOX_PX = 64  # side of the box the OpenCV trackers follow (twice the target, like STC)


class FrameTracker(Protocol):
    name: str

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None: ...

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]: ...


def grey_tensor(frame: np.ndarray, planes: list[np.ndarray] | None = None) -> torch.Tensor:
    """(1, H, W) uint8 tensor of the red-stripe response the torch trackers see (they convert
    only the context windows they crop to float, not the whole frame). ``planes``: three
    reusable (H, W) uint8 buffers (see :func:`red_response`); the tensor then shares the first
    and is valid until they are reused."""
    return torch.from_numpy(red_response(frame, out=planes)).unsqueeze(0)


class TipmPerFrame:
    """TIPM on every frame: no memory; a frame without a point is LOST (NaN)."""

    name = "tipm"

    def __init__(self) -> None:
        self.tipm = Tipm()

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        pass

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        res = self.tipm(frame)
        return res.uv, int(TrackStatus.TRACKED if res.ok else TrackStatus.LOST)


class TorchTracker:
    """EAKF-STC or plain STC from :mod:`torchseam.track`, one stream (B = 1)."""

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
    def reanchor(self, frame: np.ndarray, uv: np.ndarray) -> None:
        """Move EAKF-STC onto an absolute fix ``uv`` of this (the newest) frame."""
        self.module.reanchor(self._grey(frame), torch.tensor(np.asarray(uv)[None],
                                                               dtype=torch.float32))

    @torch.inference_mode()
    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        out = self.module.step(self._grey(frame))
        uv = out[0][0].numpy().astype(float)
        status = int(out[1][0]) if isinstance(self.module, EAKFSTC) else int(
            TrackStatus.TRACKED)
        return uv, status


class OpenCVTracker:
    """KCF / CSRT / MOSSE following a box centred on the feature point."""

    def __init__(self, name: str) -> None:
        self.name = name
        makers: dict[str, Callable[[], object]] = {
            "kcf": cv2.TrackerKCF_create, "csrt": cv2.TrackerCSRT_create,
            "mosse": cv2.legacy.TrackerMOSSE_create}
        self._make = makers[name]
        self.offset = np.zeros(2)
        self.last = np.full(2, np.nan)

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.tracker = self._make()
        h = OPENCV_BOX_PX // 2
        box = (int(round(uv[0])) - h, int(round(uv[1])) - h, OPENCV_BOX_PX, OPENCV_BOX_PX)
        self.offset = np.asarray(uv, float) - np.array([box[0] + h, box[1] + h])
        self.tracker.init(frame, box)
        self.last = np.asarray(uv, float)

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        ok, box = self.tracker.update(frame)
        if not ok:
            return self.last, int(TrackStatus.LOST)
        x, y, w, h = box
        self.last = np.array([x + w / 2, y + h / 2]) + self.offset
        return self.last, int(TrackStatus.TRACKED)


@dataclass(frozen=True)
class AnchorConfig:
    """Settings of :class:`AnchoredTracker` (``configs/anchor.yaml``; px)."""

    window_px: int = config_field(lo=16)
    gate_px: float = config_field(lo=0.0, lo_open=True)
    reanchor_px: float = config_field(lo=0.0)
    agree_px: float = config_field(lo=0.0)
    max_rms_px: float = config_field(lo=0.0, lo_open=True)


def load_anchor_config(path: str | Path | None = None) -> AnchorConfig:
    return load_config(AnchorConfig, path or CONFIG_DIR / "anchor.yaml")


class AnchoredTracker:
    """EAKF-STC with TIPM as an absolute anchor (the paper's division of labour, per frame).

    Each frame EAKF-STC tracks; TIPM then looks for the stripe corner in a window around the
    tracked point. When it finds a clean corner (its own residual and corner-angle tests)
    within ``gate_px`` of the track, that point is the output and, if the two disagree by more
    than ``reanchor_px``, EAKF-STC is moved onto it (:meth:`EAKFSTC.reanchor`: the filter keeps
    its velocity and covariance, STC re-learns its context there; a full restart left the
    filter with zero velocity and an open gate for the next frames). A corner more than
    ``agree_px`` from the track must also have tight arm fits (RMS <= ``max_rms_px``): under
    spatter TIPM sometimes takes a wrong corner a few px beside the true one, and those fits
    are looser (measured on 10 heavy sequences: wrong corners RMS 0.3-0.6 px, right ones
    median 0.17). Under arc light TIPM mostly finds nothing usable and EAKF-STC carries the
    track alone. When EAKF-STC declares the track lost (the laser went off, a long flash),
    TIPM searches the whole frame and restarts it.
    Why: in closed loop every tracking error moves the robot, which moves the image; a purely
    relative tracker can walk away with its own error, an absolute detection cannot.

    Example:
        >>> trk = AnchoredTracker()           # configs/anchor.yaml, fitted EAKF-STC
        >>> trk.init(frame0, uv0)             # doctest: +SKIP
        >>> uv, status = trk.update(frame1)   # doctest: +SKIP
    """

    name = "anchored"

    def __init__(self, model: dict | None = None, cfg: AnchorConfig | None = None) -> None:
        self.inner = TorchTracker("eakf-stc", fitted_eakf_stc(model))
        self.tipm = Tipm()
        self.cfg = cfg or load_anchor_config()

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.inner.init(frame, uv)

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        uv, status = self.inner.update(frame)
        if status == TrackStatus.LOST or not np.all(np.isfinite(uv)):
            # re-acquire: look for the stripe corner in the whole frame
            res = self.tipm(frame)
            if res.ok:
                self.inner.init(frame, res.uv)
                return res.uv, int(TrackStatus.TRACKED)
            return uv, status
        cfg = self.cfg
        h, w = frame.shape[:2]
        x0 = int(np.clip(uv[0] - cfg.window_px, 0, w - 1))
        y0 = int(np.clip(uv[1] - cfg.window_px, 0, h - 1))
        roi = np.ascontiguousarray(frame[y0:int(uv[1]) + cfg.window_px + 1,
                                         x0:int(uv[0]) + cfg.window_px + 1])
        if roi.shape[0] < 16 or roi.shape[1] < 16:
            return uv, status
        res = self.tipm(roi)
        if not res.ok:
            return uv, status
        anchor = res.uv + (x0, y0)
        gap = float(np.linalg.norm(anchor - uv))
        if gap > cfg.gate_px:
            return uv, status  # TIPM found some other corner (spatter, a reflection)
        if gap > cfg.agree_px and res.rms_px > cfg.max_rms_px:
            return uv, status  # a loose fit beside the track: likely a wrong corner
        if gap > cfg.reanchor_px:
            self.inner.reanchor(frame, anchor)
        return anchor, int(TrackStatus.TRACKED)


def fitted_eakf_stc(model: dict | None = None) -> EAKFSTC:
    """EAKF-STC with the fitted parameters of ``models/`` when present (else the paper's
    defaults, with a warning). An explicit ``model`` configuration (TrackerConfig fields) is
    taken as given: the fitted file would silently overwrite the values asked for."""
    if model:
        return EAKFSTC(model)
    from torchseam.fit.model_io import load_fitted  # the fitting stage owns the model file

    module = EAKFSTC()
    load_fitted(module)
    return module


def make_tracker(name: str, model: dict | None = None) -> FrameTracker:
    """A tracker by CLI name (see ``TRACKERS``). The EAKF-STC trackers load
    ``models/eakf_stc.safetensors`` unless ``model`` (a TrackerConfig mapping) is given."""
    if name == "eakf-stc":
        return TorchTracker(name, fitted_eakf_stc(model))
    if name == "anchored":
        return AnchoredTracker(model)
    if name == "stc":
        return TorchTracker(name, STC())
    if name == "tipm":
        return TipmPerFrame()
    if name in ("kcf", "csrt", "mosse"):
        return OpenCVTracker(name)
    raise TorchseamError(f"unknown tracker {name!r}: use one of {', '.join(TRACKERS)}")


def run_tracker(tracker: FrameTracker, frames, uv0: np.ndarray | None,
                progress: Callable[[int], None] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Track an iterable of BGR frames.

    Args:
        uv0: start point on frame 0; None: TIPM on frame 0 (it must find the stripe there).

    Returns:
        ``(uv (N, 2), status (N,), seconds (N,), init_note)``; frame 0 is the start point.
    """
    it = iter(frames)
    try:
        first = next(it)
    except StopIteration:
        raise TorchseamError("no frames to track") from None
    note = "given"
    if uv0 is None:
        res = Tipm()(first)
        if not res.ok:
            raise TorchseamError(f"frame 0: TIPM cannot start the tracker ({res.reason}); "
                                 "give the start point with --init U,V")
        uv0, note = res.uv, "TIPM on frame 0"
    tracker.init(first, np.asarray(uv0, float))
    uvs, stats, secs = [np.asarray(uv0, float)], [int(TrackStatus.TRACKED)], [0.0]
    for k, frame in enumerate(it, start=1):
        t0 = time.perf_counter()
        uv, st = tracker.update(frame)
        secs.append(time.perf_counter() - t0)
        uvs.append(np.asarray(uv, float))
        stats.append(st)
        if progress:
            progress(k)
    return np.stack(uvs), np.array(stats), np.array(secs), note
