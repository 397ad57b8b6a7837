"""A camera's frames over TCP, each with its exposure time on the camera's own clock.

The transport between a camera process and the weld: the virtual cell's laser camera serves
it (:class:`FrameStreamServer`), the weld reads it (:class:`StreamCamera`, ``tcp://HOST:PORT``
in the cell file's ``camera.source``). A camera driver of your own (a GigE Vision camera read
with Aravis, say) can serve the same stream and the weld needs nothing else.

The wire, one message per frame, little-endian (``struct`` ``<4sHHqqHHBBI``, 34 bytes, then the
pixels)::

    magic      4 bytes  b"TSFS"
    version    u16      1
    header     u16      34 (bytes of this header)
    index      i64      the camera's frame number (gaps: frames the camera lost)
    t_exp_ns   i64      start of the exposure, ns on the camera's clock
    width      u16
    height     u16
    channels   u8       1 (mono) or 3 (BGR)
    bits       u8       8 or 16
    payload    u32      width * height * channels * bits / 8 bytes of row-major pixels follow

The weld may ask the camera for an exposure on the same connection (its automatic exposure,
``camera.auto_exposure`` in the cell file), one message of 16 bytes (``<4sHHd``)::

    magic      4 bytes  b"TSXR"
    version    u16      1
    header     u16      16 (bytes of this message)
    scale      f64      the exposure asked for, as a share of the camera's configured one

A camera applies the newest request to the frames it exposes after it arrives; one that reads
none ignores them (the weld sends without waiting, and drops a request the connection cannot
take at once). :class:`FrameStreamServer` keeps the newest in :attr:`~FrameStreamServer.exposure`.

The reader stamps each frame's arrival on the PC's monotonic clock as its header is read (the
pixels follow at the link's speed); the exposure time stays on the camera's clock
(:class:`~torchseam.live.clocks.ClockOffset` relates the two). A message that breaks the
format (magic, version, sizes above ``max_pixels``) closes the connection with one line naming
the source and the field: a camera that speaks something else is never decoded as frames.
"""

from __future__ import annotations

import contextlib
import queue
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from torchseam.core.errors import TorchseamError

HEADER = struct.Struct("<4sHHqqHHBBI")
MAGIC = b"TSFS"
VERSION = 1
MAX_PIXELS = 4096 * 4096   # a frame larger than this is not a laser camera's: refused
REQUEST = struct.Struct("<4sHHd")
REQUEST_MAGIC = b"TSXR"
#: the exposure scales a request may carry (outside: the request is refused, not applied)
MIN_SCALE, MAX_SCALE = 1e-3, 1e3


class FrameStreamError(TorchseamError):
    """The frame stream broke its format or could not be reached."""


@dataclass(frozen=True)
class StampedFrame:
    """One frame as the weld receives it.

    Attributes:
        image: (H, W, 3) uint8 BGR or (H, W) uint8 / uint16 mono.
        index: the camera's frame number.
        t_exp_s: start of the exposure, s on the camera's clock.
        t_arrival_s: when its header arrived, s on the PC's monotonic clock.
    """

    image: np.ndarray
    index: int
    t_exp_s: float
    t_arrival_s: float


class NewestFrames:
    """A bounded queue of frames that drops the *oldest* when full (counted in
    :attr:`dropped`): a reader thread puts, the weld gets the newest, memory stays bounded.
    Every camera input of the weld keeps its frames in one."""

    def __init__(self, maxsize: int = 2) -> None:
        self._q: queue.Queue[StampedFrame] = queue.Queue(maxsize)
        self.dropped = 0

    def put(self, f: StampedFrame) -> None:
        while True:
            try:
                self._q.put_nowait(f)
                return
            except queue.Full:
                try:
                    self._q.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def get(self, timeout_s: float) -> StampedFrame | None:
        """The next frame, or None when none came within ``timeout_s``."""
        try:
            return self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def empty(self) -> bool:
        return self._q.empty()


def parse_url(url: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` -> (host, port); a FrameStreamError naming the URL otherwise."""
    u = urlsplit(url)
    if u.scheme != "tcp" or not u.hostname or u.port is None:
        raise FrameStreamError(f"camera source {url!r}: expected tcp://HOST:PORT")
    return u.hostname, u.port


def encode(index: int, t_exp_ns: int, image: np.ndarray) -> bytes:
    """The header of one frame (the pixels follow as ``image``'s bytes)."""
    img = np.asarray(image)
    if img.ndim == 2:
        h, w, c = *img.shape, 1
    elif img.ndim == 3 and img.shape[2] in (1, 3):
        h, w, c = img.shape
    else:
        raise FrameStreamError(f"frame {index}: shape {img.shape} is not (H, W) or (H, W, 3)")
    bits = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}.get(img.dtype)
    if bits is None:
        raise FrameStreamError(f"frame {index}: dtype {img.dtype} is not uint8 or uint16")
    return HEADER.pack(MAGIC, VERSION, HEADER.size, int(index), int(t_exp_ns), w, h, c, bits,
                       w * h * c * bits // 8)


class FrameStreamServer:
    """The camera's end: serves frames to one reader at a time (a new one replaces the old).

    Args:
        host, port: where to listen (port 0: an ephemeral one, see :attr:`address`).

    :meth:`send` never blocks the camera for long: with no reader the frame is discarded (a
    free-running camera), and a reader that stops reading for ``send_timeout_s`` is dropped.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, send_timeout_s: float = 0.5
                 ) -> None:
        self._srv = socket.create_server((host, port))
        self._srv.settimeout(0.2)
        self.send_timeout_s = send_timeout_s
        self._client: socket.socket | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.sent = 0
        self.discarded = 0      # frames with no reader connected
        #: the newest exposure the reader asked for (a share of the configured one; 1 until
        #: the reader asks), and the requests refused (bad magic, version or scale)
        self.exposure = 1.0
        self.requests = 0
        self.bad_requests = 0
        self._thread = threading.Thread(target=self._accept, name="frame-stream-accept",
                                        daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._srv.getsockname()[:2]
        return host, port

    @property
    def connected(self) -> bool:
        return self._client is not None

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(self.send_timeout_s)
            with self._lock:
                old, self._client = self._client, conn
                self.exposure = 1.0     # a new reader has asked for nothing yet
            if old is not None:
                with contextlib.suppress(OSError):
                    old.close()
            threading.Thread(target=self._requests, args=(conn,), name="frame-stream-requests",
                             daemon=True).start()

    def _requests(self, conn: socket.socket) -> None:
        """Read the reader's exposure requests on ``conn`` until it closes or sends one that
        breaks the format (counted in :attr:`bad_requests`; its later ones are not read)."""
        buf = b""
        while not self._stop.is_set():
            try:
                got = conn.recv(REQUEST.size - len(buf))
            except TimeoutError:
                continue
            except OSError:
                return
            if not got:
                return
            buf += got
            if len(buf) < REQUEST.size:
                continue
            magic, version, size, scale = REQUEST.unpack(buf)
            buf = b""
            if (magic != REQUEST_MAGIC or version != VERSION or size != REQUEST.size
                    or not MIN_SCALE <= scale <= MAX_SCALE):
                self.bad_requests += 1
                return
            with self._lock:
                if self._client is conn:
                    self.exposure = float(scale)
                    self.requests += 1

    def send(self, index: int, t_exp_ns: int, image: np.ndarray) -> bool:
        """Send one frame to the reader; False when there is none (or it just went away)."""
        with self._lock:
            conn = self._client
        if conn is None:
            self.discarded += 1
            return False
        img = np.ascontiguousarray(image)
        try:
            conn.sendall(encode(index, t_exp_ns, img))
            conn.sendall(img.tobytes() if not img.flags.c_contiguous else img.data.cast("B"))
        except OSError:
            with self._lock:
                if self._client is conn:
                    self._client = None
            with contextlib.suppress(OSError):
                conn.close()
            self.discarded += 1
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self._srv.close()
        with self._lock:
            conn, self._client = self._client, None
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.close()
        self._thread.join(timeout=1.0)


def _read_exact(sock: socket.socket, n: int, buf: bytearray | None = None) -> bytearray:
    out = bytearray(n) if buf is None else buf
    view = memoryview(out)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:], n - got)
        if k == 0:
            raise ConnectionError("the camera closed the stream")
        got += k
    return out


class QueuedCamera:
    """What the weld reads a camera through: a reader thread (``_thread``, started by the
    subclass) puts frames into a bounded queue that drops the *oldest* when the weld falls
    behind (counted in :attr:`dropped`), so the weld always gets the newest frame and memory
    stays bounded; :attr:`error` says why the frames ended. :class:`StreamCamera`,
    :class:`~torchseam.live.cameras.OpenCVCamera` and
    :class:`~torchseam.live.genicam.AravisCamera` are its kinds."""

    _thread: threading.Thread

    def __init__(self, url: str, maxsize: int) -> None:
        self.url = url
        self._frames = NewestFrames(maxsize)
        self.received = 0
        self.error: str | None = None
        #: the exposure time the weld set on the camera (us, as the camera took it); None
        #: where it set none
        self.exposure_us: float | None = None
        self._stop = threading.Event()

    @property
    def dropped(self) -> int:
        """Frames the weld did not take in time (the oldest dropped)."""
        return self._frames.dropped

    def get(self, timeout_s: float) -> StampedFrame | None:
        """The next frame, or None when none came within ``timeout_s`` (or the frames ended:
        :attr:`error` says why)."""
        return self._frames.get(timeout_s)

    def request_exposure(self, scale: float) -> None:
        """Ask the camera for the exposure ``scale`` (a share of its configured one) for the
        frames it exposes from now on; FrameStreamError where it takes none from the weld."""
        raise FrameStreamError(f"camera source {self.url}: takes no exposure request from the "
                               "weld (a tcp:// frame stream or an aravis:// GenICam camera "
                               "does): use the camera's own automatic exposure and leave "
                               "camera.auto_exposure out")

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()


class StreamCamera(QueuedCamera):
    """The weld's end: connects to ``tcp://HOST:PORT`` and reads frames on a thread into a
    bounded queue that drops the *oldest* when the weld falls behind (counted in
    :attr:`dropped`): the weld always gets the newest frame and memory stays bounded.

    Args:
        url: ``tcp://HOST:PORT``.
        connect_timeout_s: how long to keep trying to connect (the camera may start later).
        maxsize: frames queued at most.
        max_pixels: larger frames break the format (the connection is closed, see
            :attr:`error`).

    Iterating yields :class:`StampedFrame`; :meth:`get` waits for the next one with a timeout
    (None: none came), which is how the weld notices a stalled camera.
    """

    def __init__(self, url: str, connect_timeout_s: float = 30.0, maxsize: int = 2,
                 max_pixels: int = MAX_PIXELS, say: Callable[[str], Any] | None = None
                 ) -> None:
        super().__init__(url, maxsize)
        self.host, self.port = parse_url(url)
        self.max_pixels = max_pixels
        self.requests_dropped = 0
        self._sock = self._connect(connect_timeout_s, say)
        self._thread = threading.Thread(target=self._read, name="frame-stream-read", daemon=True)
        self._thread.start()

    def _connect(self, timeout_s: float, say: Callable[[str], Any] | None) -> socket.socket:
        """Connect, trying again until ``timeout_s``; ``say``: told once when the first try
        fails (a wait of up to a minute is not a silent one)."""
        end = time.monotonic() + timeout_s
        said = say is None
        while True:
            try:
                s = socket.create_connection((self.host, self.port), timeout=2.0)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(0.5)
                return s
            except OSError as e:
                if time.monotonic() > end:
                    raise FrameStreamError(f"camera source {self.url}: cannot connect within "
                                           f"{timeout_s:g} s ({e.strerror or e})") from None
                if not said:
                    assert say is not None
                    say(f"camera source {self.url}: not answering ({e.strerror or e}): "
                        f"trying for up to {timeout_s:g} s")
                    said = True
                time.sleep(0.1)

    def _header(self) -> tuple[int, int, int, int, int, int] | None:
        """The next frame's header fields, or None when the stop flag was set."""
        while not self._stop.is_set():
            try:
                raw = _read_exact(self._sock, HEADER.size)
            except TimeoutError:
                continue
            magic, version, hlen, index, t_ns, w, h, c, bits, n = HEADER.unpack(raw)
            where = f"camera source {self.url}, frame {index}"
            if magic != MAGIC or version != VERSION or hlen != HEADER.size:
                raise FrameStreamError(f"camera source {self.url}: not a torchseam frame stream "
                                       f"(magic {magic!r}, version {version})")
            if c not in (1, 3) or bits not in (8, 16):
                raise FrameStreamError(f"{where}: channels {c}, bits {bits}: expected 1 or 3, "
                                       "8 or 16")
            if w * h > self.max_pixels or w == 0 or h == 0:
                raise FrameStreamError(f"{where}: {w} x {h} pixels is beyond the limit "
                                       f"({self.max_pixels})")
            if n != w * h * c * bits // 8:
                raise FrameStreamError(f"{where}: payload {n} bytes does not match {w} x {h} "
                                       f"x {c} x {bits} bits")
            return index, t_ns, w, h, c, bits
        return None

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                head = self._header()
                if head is None:
                    return
                arrived = time.monotonic()   # its header is here: the frame arrives
                index, t_ns, w, h, c, bits = head
                n = w * h * c * bits // 8
                self._sock.settimeout(5.0)   # a frame's pixels come together
                buf = _read_exact(self._sock, n)
                self._sock.settimeout(0.5)
                dtype = np.uint8 if bits == 8 else np.uint16
                img = np.frombuffer(buf, dtype).reshape((h, w, c) if c == 3 else (h, w))
                self.received += 1
                self._frames.put(StampedFrame(img, int(index), t_ns / 1e9, arrived))
        except (ConnectionError, OSError, FrameStreamError) as e:
            if not self._stop.is_set():
                self.error = str(e) if isinstance(e, FrameStreamError) else (
                    f"camera source {self.url}: {e}")

    def request_exposure(self, scale: float) -> None:
        """Send an exposure request (see the module) without waiting: one the connection
        cannot take at once is dropped (counted in ``requests_dropped``); a scale outside
        [MIN_SCALE, MAX_SCALE] is a FrameStreamError."""
        if not MIN_SCALE <= scale <= MAX_SCALE:
            raise FrameStreamError(f"camera source {self.url}: exposure scale {scale:g} is "
                                   f"outside {MIN_SCALE:g} .. {MAX_SCALE:g}")
        try:
            sent = self._sock.send(REQUEST.pack(REQUEST_MAGIC, VERSION, REQUEST.size,
                                                float(scale)), socket.MSG_DONTWAIT)
        except OSError:
            sent = 0
        if sent != REQUEST.size:
            self.requests_dropped += 1

    def __iter__(self) -> Iterator[StampedFrame]:
        while self.alive or not self._frames.empty():
            f = self.get(0.5)
            if f is not None:
                yield f

    def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self._sock.close()
        self._thread.join(timeout=1.0)

    def __enter__(self) -> StreamCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
