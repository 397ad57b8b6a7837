"""The weld's camera input, by the cell file's ``camera.source``:

* ``tcp://HOST:PORT``: a frame stream (:class:`~torchseam.live.framestream.StreamCamera`): the
  exposure time on the camera's clock with every frame (the virtual cell's camera, a driver of
  your own);
* ``aravis://DEVICE``: a GenICam camera, GigE Vision or USB3 Vision, through Aravis
  (:class:`~torchseam.live.genicam.AravisCamera`): the camera's own frame ids and time stamps;
* ``camera:N`` or a stream URL (``rtsp://``, ``http://``): a camera OpenCV opens
  (:class:`OpenCVCamera`). It gives no exposure time: each frame is stamped when it is read,
  and its exposure is taken ``camera.latency_ms`` before that (``torchseam calibrate latency``
  measures it for such a camera too).

Each is a :class:`~torchseam.live.framestream.QueuedCamera`: it yields
:class:`~torchseam.live.framestream.StampedFrame` through ``get(timeout_s)``, with ``dropped``,
``received``, ``error`` and ``close()``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from torchseam.live.framestream import (
    FrameStreamError,
    QueuedCamera,
    StampedFrame,
    StreamCamera,
)

OPENCV_PREFIXES = ("camera:", "rtsp://", "http://", "https://")


def is_camera_source(text: str) -> bool:
    """Whether ``text`` names a camera input this module opens."""
    return text.startswith(("tcp://", "aravis://", *OPENCV_PREFIXES))


class OpenCVCamera(QueuedCamera):
    """A camera OpenCV opens, read on a thread into a bounded queue (oldest dropped), each
    frame stamped on the PC's monotonic clock as it is read (exposure and arrival alike: the
    weld's clock offset then puts the exposure ``camera.latency_ms`` earlier)."""

    def __init__(self, source: str, size: tuple[int, int] | None = None,
                 fps: float | None = None, maxsize: int = 2) -> None:
        from torchseam.core.errors import FrameError
        from torchseam.live.sources import CameraSource

        dev: int | str = source
        if source.startswith("camera:"):
            try:
                dev = int(source.split(":", 1)[1])
            except ValueError:
                raise FrameStreamError(f"camera source {source!r}: expected camera:N") from None
        try:
            self._src = CameraSource(dev, size=size, fps=fps)
        except FrameError as e:
            raise FrameStreamError(str(e)) from None
        super().__init__(source, maxsize)
        self._thread = threading.Thread(target=self._read, name="opencv-read", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for f in self._src:
                if self._stop.is_set():
                    return
                t = time.monotonic()
                self.received += 1
                self._frames.put(StampedFrame(f.image, f.index, t, t))
        except Exception as e:  # noqa: BLE001 - the weld reads the reason
            self.error = f"camera source {self.url}: {e}"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._src.close()


def open_camera(source: str, size: tuple[int, int], fps: float,
                connect_timeout_s: float = 30.0,
                exposure_us: float | None = None,
                say: Callable[[str], Any] | None = None) -> QueuedCamera:
    """The camera input for ``source`` (see the module), with the exposure time
    ``exposure_us`` set on it (a GenICam camera only: the others take none from the weld, and
    asking is refused rather than ignored); FrameStreamError naming it. ``say``: told when a
    frame stream does not answer at once (it is tried for ``connect_timeout_s``)."""
    if source.startswith("aravis://"):
        from torchseam.live.genicam import AravisCamera

        return AravisCamera(source, frame_rate_hz=fps, size=size, exposure_us=exposure_us)
    if exposure_us is not None and is_camera_source(source):
        kind = "a frame stream" if source.startswith("tcp://") else "an OpenCV camera"
        raise FrameStreamError(
            f"camera source {source}: camera.exposure_us is set, but {kind} takes no exposure "
            "time from the weld: set it on the camera's side and leave camera.exposure_us out")
    if source.startswith("tcp://"):
        return StreamCamera(source, connect_timeout_s=connect_timeout_s, say=say)
    if source.startswith(OPENCV_PREFIXES):
        return OpenCVCamera(source, size=size, fps=fps)
    raise FrameStreamError(f"camera source {source!r}: expected tcp://HOST:PORT, "
                           "aravis://DEVICE, camera:N or a stream URL")
