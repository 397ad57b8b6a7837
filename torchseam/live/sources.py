"""Frame sources for the live loop: a camera driver, a recorded folder, a video file, the simulator.

A source is anything that iterates :class:`Frame` objects and can be closed
(:class:`FrameSource`); a real camera driver implements that, most simply by subclassing
:class:`BaseSource` and writing ``__iter__``. Ready-made:

* :class:`FolderSource`: a folder in the dataset format (``00000.png`` ..., optional
  ``labels.csv`` and ``meta.json``), opened and checked by :class:`~torchseam.core.dataset.Dataset`.
  Time stamps and torch poses come from ``meta.json`` when it has them.
* :class:`VideoSource`: a video file through ``cv2.VideoCapture`` (time stamps from the
  container, or the frame rate).
* :class:`CameraSource`: a live camera OpenCV can open (device index, stream URL); time
  stamps from the host clock. :func:`open_source` takes ``camera:N`` or a URL.
* :class:`SimulatedSource`: the simulator (:func:`torchseam.sim.sequence.simulate`), with the
  true feature pixel and torch pose on every frame.
* :class:`ThreadedSource`: reads another source on a thread into a bounded queue and drops the
  *oldest* frame when the consumer falls behind (counted in :attr:`ThreadedSource.dropped`), the
  way a live camera must be read: memory stays bounded and the loop always gets the newest frame.

Every frame is checked (BGR (H, W, 3) uint8, the configured size when one is given); a bad
one raises :class:`~torchseam.core.errors.FrameError` naming the file and the frame index.
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from torchseam.core.dataset import Dataset, check_frame
from torchseam.core.errors import DatasetError, FrameError
from torchseam.core.imageio import regular_file
from torchseam.core.transforms import pose_matrix

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg")


@dataclass(frozen=True)
class Frame:
    """One camera frame and what the source knows about it.

    Attributes:
        image: (H, W, 3) uint8 BGR.
        t_s: capture time, seconds on the source's clock (monotonic within a source).
        index: frame number (file number for a folder, position for a video).
        T_B_W: (4, 4) torch TCP pose in the robot base at capture (mm), when the source
            knows it (``meta.json`` of a recording, the simulator); else None.
        label: (2,) the labelled feature pixel (u, v), when known; else None.
    """

    image: np.ndarray
    t_s: float
    index: int
    T_B_W: np.ndarray | None = None
    label: np.ndarray | None = None


@runtime_checkable
class FrameSource(Protocol):
    """What the live loop reads frames from. A camera driver implements this."""

    def __iter__(self) -> Iterator[Frame]: ...

    def close(self) -> None: ...

    def __enter__(self) -> FrameSource: ...

    def __exit__(self, *exc: object) -> None: ...


class BaseSource:
    """Context-manager plumbing for sources: subclass and write ``__iter__`` (and ``close``
    when there is something to release).

    Example (a camera driver)::

        class MyCamera(BaseSource):
            def __iter__(self):
                for k, (img, t) in enumerate(self.sdk.stream()):
                    yield Frame(check_frame(img, name=f"camera frame {k}"), t, k)
            def close(self):
                self.sdk.stop()
    """

    size: tuple[int, int] | None = None   # (width, height) every frame must have

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file (idempotent)."""

    def __enter__(self) -> BaseSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FolderSource(BaseSource):
    """Frames of a dataset-format folder, in frame-number order.

    Args:
        root: the folder.
        size: (width, height) every frame must have (None: any size).
        fps: frame rate for time stamps when ``meta.json`` has none (default 25).

    Time stamps: ``meta.json`` ``frames[i].t_s`` when present, else ``frame / fps``. Torch
    poses: ``meta.json`` ``frames[i].tcp_pose`` (position_mm, quaternion w, x, y, z) when
    present. Labels: ``labels.csv``.

    Raises:
        DatasetError: no folder, no frames, bad ``labels.csv`` or ``meta.json`` (named).
        FrameError: while iterating, a frame that cannot be read or has the wrong format.
    """

    def __init__(self, root: str | os.PathLike[str], size: tuple[int, int] | None = None,
                 fps: float = 25.0) -> None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.ds = Dataset.open(root)
        self.root = self.ds.root
        self.size = size
        self.fps = float(fps)
        self.t_s, self.poses = self._meta_frames()

    def __len__(self) -> int:
        return len(self.ds)

    def _meta_frames(self) -> tuple[np.ndarray, list[np.ndarray | None]]:
        """Per-frame time stamps (N,) and torch poses from meta.json (or defaults)."""
        frames = self.ds.frames
        t = frames.astype(float) / self.fps
        poses: list[np.ndarray | None] = [None] * len(frames)
        meta = self.ds.meta
        if not meta or "frames" not in meta:
            return t, poses
        where = self.root / "meta.json"
        entries = meta["frames"]
        if not isinstance(entries, list):
            raise DatasetError(f"{where}: 'frames' must be a list")
        pos = {int(f): i for i, f in enumerate(frames)}
        for j, e in enumerate(entries):
            try:
                f = int(e["frame"])
            except (KeyError, TypeError, ValueError):
                raise DatasetError(f"{where}: frames[{j}]: no whole-number 'frame'") from None
            if f not in pos:
                continue  # truth of a frame that is not in the folder: nothing to attach it to
            i = pos[f]
            try:
                if "t_s" in e:
                    t[i] = float(e["t_s"])
                if "tcp_pose" in e:
                    tp = e["tcp_pose"]
                    T = pose_matrix(np.asarray(tp["position_mm"], float),
                                    np.asarray(tp["quaternion"], float))
                    if T.shape != (4, 4) or not np.isfinite(T).all():
                        raise ValueError("not a finite pose")
                    poses[i] = T
            except (KeyError, TypeError, ValueError) as err:
                raise DatasetError(f"{where}: frames[{j}] (frame {f}): bad t_s or tcp_pose "
                                   f"({err})") from None
        if np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0)) + 1
            raise DatasetError(f"{where}: time stamps must increase; frame {frames[k]} has "
                               f"t_s {t[k]:g} after {t[k - 1]:g}")
        return t, poses

    def __iter__(self) -> Iterator[Frame]:
        labels = self.ds.labels
        for i, f in enumerate(self.ds.frames):
            try:
                img = self.ds.read(i, self.size)
            except FrameError as e:
                raise FrameError(f"frame {int(f)}: {e}") from None
            lab = None if labels is None or np.isnan(labels[i, 0]) else labels[i].copy()
            yield Frame(img, float(self.t_s[i]), int(f), self.poses[i], lab)


class VideoSource(BaseSource):
    """Frames of a video file (anything ``cv2.VideoCapture`` decodes: MP4, AVI, ...).

    Args:
        path: the video file.
        size: (width, height) every frame must have (None: any size).
        fps: frame rate for time stamps when the container's own are missing (default: the
            file's frame rate, else 25).

    Time stamps come from ``CAP_PROP_POS_MSEC`` while they increase, else ``index / fps``.
    Videos carry no poses or labels (``Frame.T_B_W`` and ``label`` are None).

    Raises:
        FrameError: the file does not exist or cannot be opened as a video (named), or a
            decoded frame has the wrong format (named with its index).
    """

    def __init__(self, path: str | os.PathLike[str], size: tuple[int, int] | None = None,
                 fps: float | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FrameError(f"{self.path}: no such video file")
        self.size = size
        self._cap: Any = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            self._cap.release()
            raise FrameError(f"{self.path}: cannot be opened as a video (not a video file, or "
                             "OpenCV has no decoder for it)")
        file_fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = float(fps) if fps else (file_fps if 0 < file_fps < 1e4 else 25.0)
        n = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self.frame_count = n if n > 0 else None   # the container's claim (may be absent)

    def __iter__(self) -> Iterator[Frame]:
        cap = self._cap
        if cap is None:
            raise FrameError(f"{self.path}: the video source is closed")
        k, last_t = 0, -math.inf
        while True:
            ok, img = cap.read()
            if not ok:
                if k == 0:
                    raise FrameError(f"{self.path}: no frame could be decoded")
                return
            t_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
            t = t_ms / 1e3 if math.isfinite(t_ms) and t_ms / 1e3 > last_t else k / self.fps
            if t <= last_t:  # container time stamps missing or stuck: the frame rate
                t = last_t + 1.0 / self.fps
            last_t = t
            img = check_frame(img, self.size, f"{self.path}: frame {k}")
            yield Frame(img, t, k)
            k += 1

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class CameraSource(BaseSource):
    """Live frames of a camera OpenCV can open: a device index (a UVC / V4L2 camera: ``0``)
    or a stream URL (``rtsp://...``, ``http://...``). A GigE Vision camera with a vendor SDK
    needs its own driver (a :class:`BaseSource` subclass, see its example).

    Args:
        device: device index or URL.
        size: (width, height): asked of the camera, and every frame must have it (a camera
            that ignores the request gives a named :class:`FrameError` on its first frame,
            rather than a calibration silently applied to the wrong image size).
        fps: frame rate to ask of the camera (None: its default).
        max_failed_reads: consecutive failed reads after which the camera counts as gone
            (unplugged, stream ended): the source ends with an error naming it. Single
            failed reads are skipped: the live loop sees a late frame and holds if too late.

    Time stamps: the host's monotonic clock at each read, from the first frame (a live
    camera has no file time); ``Frame.index`` counts the frames delivered.

    Raises:
        FrameError: the camera cannot be opened (named), a frame has the wrong format, or
            the camera stops delivering.
    """

    def __init__(self, device: int | str, size: tuple[int, int] | None = None,
                 fps: float | None = None, max_failed_reads: int = 25) -> None:
        self.device = device
        self.name = f"camera {device!r}"
        self.size = size
        self.max_failed_reads = int(max_failed_reads)
        # OpenCV's own warnings about a device it cannot open (a second stderr line beside
        # the one error below) are held back while it tries
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            self._cap: Any = cv2.VideoCapture(device)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not self._cap.isOpened():
            self._cap.release()
            raise FrameError(f"{self.name}: cannot be opened (no such device, in use by "
                             "another program, or no OpenCV backend for it)")
        if size is not None:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        if fps:
            self._cap.set(cv2.CAP_PROP_FPS, float(fps))
        cam_fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = float(fps) if fps else (cam_fps if 0 < cam_fps < 1e4 else 25.0)

    def __iter__(self) -> Iterator[Frame]:
        cap = self._cap
        if cap is None:
            raise FrameError(f"{self.name}: the camera source is closed")
        k, failed, t0 = 0, 0, None
        while True:
            ok, img = cap.read()
            t = time.monotonic()
            if not ok:
                failed += 1
                if failed >= self.max_failed_reads:
                    raise FrameError(f"{self.name}: no frame in {failed} reads after frame "
                                     f"{k - 1} (unplugged, or the stream ended)")
                continue
            failed = 0
            t0 = t if t0 is None else t0
            img = check_frame(img, self.size, f"{self.name}: frame {k}")
            yield Frame(img, t - t0, k)
            k += 1

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class SimulatedSource(BaseSource):
    """The simulator as a frame source (open loop: the torch follows the nominal path).

    Args:
        cell, part, noise: configurations; spec: :class:`~torchseam.sim.sequence.SequenceSpec`.

    Every frame carries the true torch pose and the true feature pixel; ``truths`` collects
    the full ground truth of the frames yielded so far.
    """

    def __init__(self, cell: Any, part: Any, noise: Any, spec: Any) -> None:
        self.cell, self.part, self.noise, self.spec = cell, part, noise, spec
        self.size = (cell.camera.width, cell.camera.height)
        self.truths: list[Any] = []

    def __iter__(self) -> Iterator[Frame]:
        from torchseam.sim.sequence import simulate

        for img, truth in simulate(self.cell, self.part, self.noise, self.spec):
            self.truths.append(truth)
            lab = truth.uv.copy() if np.all(np.isfinite(truth.uv)) else None
            yield Frame(img, float(truth.t_s), int(truth.index), truth.T_B_W.copy(), lab)


_END = object()


class ThreadedSource(BaseSource):
    """Reads ``source`` on a background thread into a bounded queue (a live camera's reader).

    When the consumer falls behind, the oldest queued frame is dropped for the new one and
    counted in :attr:`dropped`: memory stays bounded and the loop sees the newest frames. An
    error in the reader (a bad frame, a camera fault) is raised in the consumer.

    Args:
        source: any :class:`FrameSource`.
        maxsize: frames queued at most (>= 1).
    """

    def __init__(self, source: FrameSource, maxsize: int = 4) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be >= 1, got {maxsize}")
        self.source = source
        self.size = getattr(source, "size", None)
        self.maxsize = maxsize
        self.dropped = 0
        self._q: queue.Queue[Any] = queue.Queue(maxsize)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def _put(self, item: Any) -> None:
        """Queue without blocking: a full queue loses its oldest frame (counted)."""
        with self._lock:
            while True:
                try:
                    self._q.put_nowait(item)
                    return
                except queue.Full:
                    try:
                        old = self._q.get_nowait()
                    except queue.Empty:
                        continue
                    if isinstance(old, Frame):
                        self.dropped += 1

    def _read(self) -> None:
        try:
            for f in self.source:
                if self._stop.is_set():
                    return
                self._put(f)
        except BaseException as e:  # handed to the consumer
            self._put(e)
            return
        self._put(_END)

    def __iter__(self) -> Iterator[Frame]:
        if self._thread is None:
            self._thread = threading.Thread(target=self._read, name="frame-reader",
                                            daemon=True)
            self._thread.start()
        while True:
            item = self._q.get()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.source.close()


def open_source(path: str | os.PathLike[str], size: tuple[int, int] | None = None,
                fps: float | None = None) -> FolderSource | VideoSource | ThreadedSource:
    """A folder -> :class:`FolderSource`, a file -> :class:`VideoSource`, ``camera:N`` or a
    stream URL (``rtsp://...``) -> :class:`CameraSource` read by a :class:`ThreadedSource`
    (a live camera does not wait for the loop: the newest frame is the one to track).

    Raises:
        DatasetError / FrameError: nothing at ``path``, or it cannot be read (named).
    """
    text = os.fspath(path)
    if text.startswith("camera:"):
        dev = text[len("camera:"):]
        if not dev:
            raise FrameError(f"{text!r}: give the camera as camera:N (a device index) or a "
                             "stream URL")
        return ThreadedSource(CameraSource(int(dev) if dev.isdigit() else dev, size, fps))
    if "://" in text:
        return ThreadedSource(CameraSource(text, size, fps))
    p = Path(path)
    if p.is_dir():
        return FolderSource(p, size, fps or 25.0)
    if p.is_file():
        return VideoSource(p, size, fps)
    if p.exists():   # a FIFO, a socket, a device: said so, never opened (a FIFO would block)
        regular_file(p)
    raise DatasetError(f"{p}: no such folder or video file (a camera: camera:N or a stream "
                       "URL)")


__all__ = ["BaseSource", "CameraSource", "Frame", "FolderSource", "FrameSource", "SimulatedSource",
           "ThreadedSource", "VideoSource", "open_source"]
