"""Industrial GenICam cameras (GigE Vision, USB3 Vision) through Aravis, with the camera's own
time stamps: the weld's camera input for ``camera.source: aravis://DEVICE`` in a cell file.

``DEVICE`` is what Aravis opens: the camera's address (``aravis://192.168.10.20``), its device
id (``aravis://Basler-21234567``), or nothing for the first camera found (``aravis://``). The
optional extra installs the binding: ``pip install -c constraints-cpu.txt ".[genicam]"`` (the
``aravis-python`` wheel, which carries libaravis, and PyGObject; on Debian PyGObject builds
against ``libgirepository1.0-dev libcairo2-dev pkg-config``).

Each buffer gives a :class:`~torchseam.live.framestream.StampedFrame`: the pixels (Mono8,
Mono16; Bayer and RGB8 converted to BGR with OpenCV), the camera's frame id, the exposure time
stamp on the camera's clock (``arv_buffer_get_timestamp``: the device's tick counter, in ns)
and the arrival on the PC's monotonic clock (from Aravis' host time stamp of the buffer). A
buffer that came incomplete (lost packets) is not a frame: it is counted in :attr:`incomplete`
and skipped, the gap shows in the frame ids.
"""

from __future__ import annotations

import threading
import time
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from torchseam.live.framestream import FrameStreamError, QueuedCamera, StampedFrame

N_BUFFERS = 8


def load_aravis() -> Any:
    """The Aravis GObject binding, or a FrameStreamError saying how to install it."""
    try:
        from aravis import Aravis  # the aravis-python wheel (needs PyGObject)
    except Exception as e:  # noqa: BLE001 - ImportError, or gi's own errors
        raise FrameStreamError(
            "camera source aravis://...: the GenICam extra is not installed "
            f"({type(e).__name__}: {e}); pip install -c constraints-cpu.txt "
            "'torchseam[genicam]'") from None
    return Aravis


def device_of(url: str) -> str | None:
    """``aravis://DEVICE`` -> DEVICE (None: the first camera)."""
    u = urlsplit(url)
    if u.scheme != "aravis":
        raise FrameStreamError(f"camera source {url!r}: expected aravis://DEVICE")
    dev = (u.netloc + u.path).strip("/")
    return dev or None


def _to_image(buf: Any, fmt: str) -> np.ndarray:
    import cv2

    w, h = buf.get_image_width(), buf.get_image_height()
    data = buf.get_data()
    if fmt == "Mono8":
        return np.frombuffer(data, np.uint8, w * h).reshape(h, w).copy()
    if fmt in ("Mono10", "Mono12", "Mono14", "Mono16"):
        return np.frombuffer(data, np.uint16, w * h).reshape(h, w).copy()
    if fmt == "RGB8":
        return cv2.cvtColor(np.frombuffer(data, np.uint8, w * h * 3).reshape(h, w, 3),
                            cv2.COLOR_RGB2BGR)
    if fmt == "BGR8":
        return np.frombuffer(data, np.uint8, w * h * 3).reshape(h, w, 3).copy()
    bayer = {"BayerRG8": cv2.COLOR_BayerRG2BGR, "BayerBG8": cv2.COLOR_BayerBG2BGR,
             "BayerGR8": cv2.COLOR_BayerGR2BGR, "BayerGB8": cv2.COLOR_BayerGB2BGR}.get(fmt)
    if bayer is not None:
        return cv2.cvtColor(np.frombuffer(data, np.uint8, w * h).reshape(h, w), bayer)
    raise FrameStreamError(f"pixel format {fmt}: not read (Mono8/10/12/14/16, RGB8, BGR8, "
                           "Bayer*8)")


class AravisCamera(QueuedCamera):
    """A GenICam camera through Aravis, read on a thread into a bounded queue that drops the
    oldest frame when the weld falls behind (the same interface as
    :class:`~torchseam.live.framestream.StreamCamera`).

    Args:
        url: ``aravis://DEVICE``.
        frame_rate_hz: set on the camera when given (AcquisitionFrameRate).
        size: (width, height) region set on the camera when given.
        maxsize: frames queued at most.
        exposure_us: the exposure time set on the camera when given (ExposureTime, auto
            exposure off), microseconds; refused (FrameStreamError) outside the camera's
            bounds or longer than the frame period. ``self.exposure_us``: as the camera took
            it (its own step), None when not set.
    """

    def __init__(self, url: str, frame_rate_hz: float | None = None,
                 size: tuple[int, int] | None = None, maxsize: int = 2,
                 exposure_us: float | None = None) -> None:
        Aravis = load_aravis()
        super().__init__(url, maxsize)
        try:
            self.camera = Aravis.Camera.new(device_of(url))
        except Exception as e:  # noqa: BLE001 - GLib.Error
            raise FrameStreamError(f"camera source {url}: Aravis cannot open it ({e})") from None
        if size is not None:
            self.camera.set_region(0, 0, int(size[0]), int(size[1]))
        if exposure_us is not None:
            self.exposure_us = self._set_exposure(Aravis, float(exposure_us), frame_rate_hz)
        if frame_rate_hz is not None:
            self.camera.set_frame_rate(float(frame_rate_hz))
        self._Aravis, self._frame_rate_hz = Aravis, frame_rate_hz
        #: the exposure time (us) a request's scale multiplies: as set, or the camera's at open
        self.base_exposure_us: float | None = None
        if self.camera.is_exposure_time_available():
            self.base_exposure_us = (self.exposure_us if self.exposure_us is not None
                                     else float(self.camera.get_exposure_time()))
        self.pixel_format = self.camera.get_pixel_format_as_string()
        self.model = f"{self.camera.get_vendor_name()} {self.camera.get_model_name()}"
        self._stream = self.camera.create_stream(None, None)
        payload = self.camera.get_payload()
        for _ in range(N_BUFFERS):
            self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self._ok = Aravis.BufferStatus.SUCCESS
        self.incomplete = 0
        self.camera.start_acquisition()
        self._thread = threading.Thread(target=self._read, name="aravis-read", daemon=True)
        self._thread.start()

    def _set_exposure(self, Aravis: Any, us: float, frame_rate_hz: float | None) -> float:
        """Set the exposure time ``us`` (before the frame rate: a long exposure bounds it);
        the time the camera took. Refused where the camera has none, outside its bounds (a
        camera may store any number it is sent) or over the frame period."""
        where = f"camera source {self.url}: camera.exposure_us {us:g}"
        if not self.camera.is_exposure_time_available():
            raise FrameStreamError(f"{where}: the camera has no exposure time to set")
        lo, hi = self.camera.get_exposure_time_bounds()
        if not lo <= us <= hi:
            raise FrameStreamError(f"{where} is outside what the camera takes ({lo:g} .. "
                                   f"{hi:g} us)")
        if frame_rate_hz is not None and us > 1e6 / frame_rate_hz:
            raise FrameStreamError(f"{where} is longer than the frame period at "
                                   f"{frame_rate_hz:g} frames/s ({1e6 / frame_rate_hz:g} us)")
        if self.camera.is_exposure_auto_available():
            self.camera.set_exposure_time_auto(Aravis.Auto.OFF)
        self.camera.set_exposure_time(us)
        return float(self.camera.get_exposure_time())

    def request_exposure(self, scale: float) -> None:
        """Set the exposure time to ``scale`` x :attr:`base_exposure_us`, within the camera's
        bounds and the frame period (the camera's own automatic exposure off);
        ``self.exposure_us`` is then the time the camera took. FrameStreamError where the
        camera has no exposure time to set."""
        if self.base_exposure_us is None:
            raise FrameStreamError(f"camera source {self.url}: the camera has no exposure "
                                   "time to set: leave camera.auto_exposure out")
        lo, hi = self.camera.get_exposure_time_bounds()
        if self._frame_rate_hz is not None:
            hi = min(hi, 1e6 / self._frame_rate_hz)
        if self.camera.is_exposure_auto_available():
            self.camera.set_exposure_time_auto(self._Aravis.Auto.OFF)
        self.camera.set_exposure_time(min(max(self.base_exposure_us * float(scale), lo), hi))
        self.exposure_us = float(self.camera.get_exposure_time())

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                buf = self._stream.timeout_pop_buffer(200_000)   # us
                if buf is None:
                    continue
                try:
                    if buf.get_status() != self._ok:
                        self.incomplete += 1
                        continue
                    # the host's arrival stamp (CLOCK_REALTIME ns) onto the monotonic clock
                    arrived = time.monotonic() - (time.time_ns() - buf.get_system_timestamp()
                                                  ) / 1e9
                    img = _to_image(buf, self.pixel_format)
                    f = StampedFrame(img, int(buf.get_frame_id()), buf.get_timestamp() / 1e9,
                                     arrived)
                finally:
                    self._stream.push_buffer(buf)
                self.received += 1
                self._frames.put(f)
        except Exception as e:  # noqa: BLE001 - the weld reads the reason
            self.error = f"camera source {self.url}: {e}"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        try:
            self.camera.stop_acquisition()
        except Exception:  # noqa: BLE001, S110 - closing a camera that went away
            pass

    def __enter__(self) -> AravisCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
