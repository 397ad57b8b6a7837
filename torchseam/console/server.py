"""The console's web server: one page, a JSON control API and a WebSocket push stream (aiohttp).

* ``GET /`` the page (``static/console.html``, self-contained: no CDN, works offline).
* ``GET /ws`` the push stream. Text messages are JSON: first ``hello`` (settings, parameter
  defaults and choices, and the full history from the ring buffers: a new tab or a reload
  joins a running weld without touching it), then ``update`` at ``publish.rate_hz`` (only
  what is newer than what this client has, plus the status and link state). Binary messages
  are the newest camera frame as JPEG (drawn feature point and status), at most
  ``publish.jpeg_rate_hz`` (and ``publish.rate_hz``), only when there is a new one.
* ``POST /api/start`` (JSON weld parameters; a field left out takes the form's default),
  ``/api/hold``, ``/api/resume``, ``/api/stop``:
  200 ``{"ok": true}``, or 400 / 409 ``{"error": "..."}`` with a message for the operator.
* ``GET /api/state`` the same snapshot as ``hello``; ``GET /frame.jpg`` the newest frame;
  ``GET /api/auth`` 200 when the request carries the token (the page asks when its stream
  closes, to tell a wrong token from a console that is gone).

Who may ask (:meth:`ConsoleServer.refusal`, every request): the ``Host`` header must name this
console (``localhost``, ``127.0.0.1`` or ``[::1]`` with the served port, or the ``--host`` it is
bound to, or a name given with ``--allow-host``), so a DNS-rebinding page (its own name
resolving to 127.0.0.1) is refused; an ``Origin`` header, when there is one, must name the same;
and everything but ``GET`` of the page, ``/api/state`` and ``/frame.jpg`` must carry the per-run
token (``secrets.token_urlsafe``, printed with the address at start: ``/?token=...``) in the
``X-Torchseam-Token`` header, or for the WebSocket in the ``token`` query parameter (a browser
cannot set a WebSocket's headers). Refusals are 403 ``{"ok": false, "error": "..."}``.

The operator keeps a path in (:class:`ConnectionGuard`, ``server:`` settings): connections are
capped per client address and in all, within the file descriptors the process may open, the
oldest idle one making way for a new one; idle and slow-header connections are closed after
``idle_timeout_s``, a request's answer is bounded by ``request_timeout_s``; a malformed request
is one log line, rate-limited (:class:`BadRequestLog`). Every response carries
``X-Frame-Options: DENY``, ``X-Content-Type-Options: nosniff``, ``Referrer-Policy:
no-referrer`` and a Content-Security-Policy with ``frame-ancestors 'none'``; the page's allows
exactly its own inline code, by hash (:func:`page_csp`).

Nothing here runs on the weld thread. One publisher task encodes the newest frame (on a worker
thread: OpenCV releases the GIL) and wakes each client's sender; a sender sends what is new
since its own cursor, so a slow client skips frames and merges updates instead of queueing
them (its backlog is one cursor, never a growing queue), and a client that takes longer than
``server.send_timeout_s`` for one message is dropped.
"""

from __future__ import annotations

import asyncio
import base64
import concurrent.futures
import functools
import hashlib
import hmac
import ipaddress
import json
import logging
import math
import os
import secrets
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from html.parser import HTMLParser
from importlib import resources
from typing import Any
from urllib.parse import urlsplit

import cv2
import numpy as np
from aiohttp import WSMsgType, http_exceptions, web

from torchseam.console.config import ConsoleConfig, ParamError, ServerSettings, WeldParams
from torchseam.console.session import Cursor, LatestFrame, WeldSession, num
from torchseam.core.overlay import put_label

#: Colours (BGR) of the tracker's status: TRACKED, COASTING, LOST (as in the demo video).
STATUS_BGR = {0: (0, 255, 0), 1: (0, 200, 255), 2: (0, 0, 255)}
STATUS_NAMES = {0: "tracked", 1: "coasting", 2: "lost"}
TRUTH_BGR = (255, 160, 0)
MARKER_PX = 14              # feature-point cross size on the (scaled) frame
FONT_SCALE = 0.4
#: The robot-link panel's text when the loop's poses go to no controller (a replay).
NO_CONTROLLER = "replay: no controller"

#: Header carrying the per-run token on API calls; the WebSocket takes it as ``?token=``.
TOKEN_HEADER = "X-Torchseam-Token"
TOKEN_PARAM = "token"
#: Host names every console answers to (with its port), whatever it is bound to.
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "[::1]")
#: What may be fetched without the token (``GET`` / ``HEAD`` only): the page, which then reads
#: the token from its own address, and read-only state.
TOKEN_FREE = frozenset({"/", "/api/state", "/frame.jpg"})
#: Largest request body (the parameter form is about 250 bytes).
MAX_BODY = 16 * 1024
#: Deepest JSON accepted (the form is an object holding one list: 2).
MAX_JSON_DEPTH = 4
#: Longest number literal accepted in a JSON body (digits, sign, point, exponent).
MAX_NUMBER_CHARS = 32


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _host_name(name: str) -> str:
    """A host name as it appears in a ``Host`` header: lower case, IPv6 in brackets."""
    name = name.strip().lower()
    bare = name[1:-1] if name.startswith("[") and name.endswith("]") else name
    try:
        ip = ipaddress.ip_address(bare)
    except ValueError:
        return name
    return f"[{ip.compressed}]" if ip.version == 6 else ip.compressed


def split_host(value: str, default_port: int = 80) -> tuple[str, int] | None:
    """``(name, port)`` of a ``Host`` header value (``name[:port]``, ``[v6][:port]``), None
    when it is not one."""
    v = value.strip().lower()
    if v.startswith("["):
        end = v.find("]")
        if end < 0:
            return None
        name, rest = v[:end + 1], v[end + 1:]
    else:
        name, sep, rest = v.partition(":")
        rest = sep + rest
    if not name:
        return None
    if not rest:
        port = default_port
    elif rest[0] == ":" and 1 < len(rest) <= 6 and rest[1:].isascii() and rest[1:].isdigit():
        port = int(rest[1:])
    else:
        return None
    return _host_name(name), port


class _JsonRefused(ValueError):
    """A request body refused before it reaches the parameters (the message names why)."""


@dataclass(frozen=True)
class _LongNumber:
    """A JSON number literal too long to convert (the 4300-digit limit of ``int``, a float
    that overflows): kept as text, refused by name once its key is known."""

    text: str


def _number_literal(conv: Callable[[str], Any]) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        return _LongNumber(text) if len(text) > MAX_NUMBER_CHARS else conv(text)
    return parse


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook``: refuse a key given twice and a number too long (by its key)."""
    out: dict[str, Any] = {}
    for k, v in pairs:
        name = k if len(k) <= 40 else k[:32] + "..."
        if k in out:
            raise _JsonRefused(f"{name}: given twice")
        for i, item in enumerate(v if isinstance(v, list) else [v]):
            if isinstance(item, _LongNumber):
                where = f"{name}[{i}]" if isinstance(v, list) else name
                raise _JsonRefused(f"{where}: a number of {len(item.text)} characters is too "
                                   f"long (at most {MAX_NUMBER_CHARS})")
        out[k] = v
    return out


def _json_depth_exceeds(text: str, limit: int) -> bool:
    """True when ``text`` nests arrays / objects deeper than ``limit`` (checked before
    ``json.loads``, whose recursion a body of brackets would exhaust)."""
    depth = 0
    in_str = esc = False
    for ch in text:
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if depth > limit:
                return True
        elif ch in "]}":
            depth -= 1
    return False


def parse_body(body: bytes) -> Any:
    """The JSON of a request body, guarded: nesting deeper than :data:`MAX_JSON_DEPTH`, number
    literals longer than :data:`MAX_NUMBER_CHARS`, keys given twice and non-JSON raise
    :class:`ValueError` with the operator's message (naming the field where there is one)."""
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise _JsonRefused("parameters: the request is not UTF-8 JSON") from None
    if _json_depth_exceeds(text, MAX_JSON_DEPTH):
        raise _JsonRefused(f"parameters: JSON nested deeper than {MAX_JSON_DEPTH} levels")
    if not text.strip():
        return {}
    try:
        raw = json.loads(text, parse_int=_number_literal(int),
                         parse_float=_number_literal(float), object_pairs_hook=_pairs)
    except _JsonRefused:
        raise
    except (ValueError, RecursionError):
        raise _JsonRefused("parameters: the request is not JSON") from None
    if isinstance(raw, _LongNumber):
        raise _JsonRefused("parameters: expected a JSON object")
    if isinstance(raw, list) and any(isinstance(x, _LongNumber) for x in raw):
        raise _JsonRefused("parameters: expected a JSON object")
    return raw


def render_frame(lf: LatestFrame, scale: float, quality: int) -> bytes:
    """The camera frame, shrunk by ``scale``, with the feature point (and the simulator's true
    point), the tracker status and the loop state drawn; JPEG bytes."""
    img = lf.image
    if scale != 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    else:
        img = img.copy()
    if img.ndim == 2:  # a mono camera: draw the marks in colour
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    colour = STATUS_BGR.get(lf.status, STATUS_BGR[2])
    if lf.uv_true is not None and np.all(np.isfinite(lf.uv_true)):
        c = tuple(int(round(x * scale)) for x in lf.uv_true)
        cv2.circle(img, c, 3, TRUTH_BGR, 1, cv2.LINE_AA)
    if lf.uv is not None:
        c = tuple(int(round(x * scale)) for x in lf.uv)
        cv2.drawMarker(img, c, colour, cv2.MARKER_CROSS, MARKER_PX, 1, cv2.LINE_AA)
        cv2.circle(img, c, MARKER_PX // 2 + 2, colour, 1, cv2.LINE_AA)
    h, w = img.shape[:2]
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), colour, 2)
    text = f"{lf.seg}  {STATUS_NAMES.get(lf.status, '?')}  {lf.state}  t={lf.t_s:.2f}s"
    put_label(img, text, (6, 16), FONT_SCALE)
    if lf.message:
        put_label(img, lf.message[:60], (6, h - 8), FONT_SCALE, (0, 200, 255))
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


@dataclass
class _Jpeg:
    seq: int
    data: bytes


#: The longest a publisher tick waits for the weld's next frame (a camera's frame period is
#: shorter): without a frame by then (held, stopped, a slow source) it ticks anyway.
FRAME_WAIT_S = 0.1


@dataclass(eq=False)
class _Client:
    ws: web.WebSocketResponse
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    jpeg_seq: int = -1
    sent: int = 0


# --------------------------------------------------------------------------- operator's path

#: Headers on every response (the page's CSP is built from the page: :func:`page_csp`).
SECURITY_HEADERS = {"X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff",
                    "Referrer-Policy": "no-referrer"}
#: The Content-Security-Policy of every response but the page (JSON, JPEG, errors): nothing
#: may run, load or frame it.
CSP_STRICT = "default-src 'none'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"


class _InlineCode(HTMLParser):
    """The page's inline code: ``<script>`` / ``<style>`` bodies, event-handler and ``style``
    attributes (attribute values as the browser hashes them: entities decoded)."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.scripts: list[str] = []
        self.styles: list[str] = []
        self.handlers: list[str] = []
        self.style_attrs: list[str] = []
        self.external: list[str] = []
        self._open: str | None = None
        self._text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for name, value in attrs:
            if value is None:
                continue
            if name == "style":
                self.style_attrs.append(value)
            elif name.startswith("on"):
                self.handlers.append(value)
            elif name == "src" and tag == "script":
                self.external.append(value)
        if tag in ("script", "style"):
            self._open, self._text = tag, []

    def handle_data(self, data: str) -> None:
        if self._open is not None:
            self._text.append(data)

    def handle_endtag(self, tag: str) -> None:
        if tag == self._open:
            (self.scripts if tag == "script" else self.styles).append("".join(self._text))
            self._open = None


def _sha256(text: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"


def _sources(code: list[str], attrs: list[str]) -> str:
    """A source list allowing exactly ``code`` (inline elements) and ``attrs`` (attributes,
    which CSP allows by hash only with ``'unsafe-hashes'``), or ``'none'``."""
    out = sorted({_sha256(c) for c in code})
    if attrs:
        out += ["'unsafe-hashes'", *sorted({_sha256(a) for a in attrs})]
    return " ".join(out) or "'none'"


def page_csp(html: str, allow_eval: bool = False) -> str:
    """The page's Content-Security-Policy: its own inline script and style by SHA-256 hash
    (and its event-handler and ``style`` attributes, ``'unsafe-hashes'``), images from itself
    and ``blob:`` (the camera frame), fetch and WebSocket to itself, nothing else; no
    framing (``frame-ancestors 'none'``), no ``<base>``, no form posts. An injected script
    or handler has another hash and does not run. ``allow_eval``: ``'unsafe-eval'`` too
    (``server.page_allows_eval``: for browser automation that evaluates in the page)."""
    found = _InlineCode()
    found.feed(html)
    found.close()
    if found.external:
        raise ValueError(f"the page loads scripts ({found.external[0]!r}): it must be "
                         "self-contained")
    return "; ".join([
        "default-src 'none'",
        f"script-src {_sources(found.scripts, found.handlers)}"
        + (" 'unsafe-eval'" if allow_eval else ""),
        f"style-src {_sources(found.styles, found.style_attrs)}",
        "img-src 'self' blob:", "connect-src 'self'", "base-uri 'none'",
        "form-action 'none'", "frame-ancestors 'none'"])


def _secure(headers: Any) -> None:
    """The security headers onto a response's headers (the page's own CSP kept)."""
    headers.setdefault("Content-Security-Policy", CSP_STRICT)
    for k, v in SECURITY_HEADERS.items():
        headers.setdefault(k, v)


class _SecureRequest(web.Request):
    """A request whose responses carry :data:`SECURITY_HEADERS`, aiohttp's own included (the
    400 for a request it cannot parse goes to no middleware and no signal)."""

    async def _prepare_hook(self, response: web.StreamResponse) -> None:
        await super()._prepare_hook(response)
        _secure(response.headers)


@dataclass(eq=False)
class _Conn:
    transport: Any
    peer: str
    idle_since: float
    busy: int = 0


def _peer(transport: Any) -> str:
    name = transport.get_extra_info("peername") if transport is not None else None
    return str(name[0]) if isinstance(name, tuple) and name else str(name)


class ConnectionGuard:
    """Keeps a path open to the console for its operator, whatever else connects.

    aiohttp accepts every connection and keeps it as long as the peer likes; 1 100 idle ones
    exhausted a 1 024-descriptor process and the operator's ``stop`` timed out (issue 36).
    The guard sees every connection open and close (:meth:`attach`) and every request start
    and end (the ``busy`` / ``idle`` calls of the server's middleware), and keeps:

    * at most ``max_connections_per_client`` per address and :attr:`limit` in all
      (``server.max_connections``, less when the descriptor limit leaves less room: see
      :meth:`plan`). A new connection past either cap closes the *oldest idle* one (no request
      being answered: it sent nothing, or half a header, or sits between requests), of that
      address first: the newest connection, the operator's request, is served. Only when every
      one is answering a request is the new one closed instead;
    * no connection idle longer than ``idle_timeout_s`` (:meth:`sweep`): one that never sends
      a request, sends its header byte by byte, or idles between requests.

    Closing is ``abort()``: at once, whatever the peer has not read.
    """

    def __init__(self, settings: ServerSettings, clock: Callable[[], float] = time.monotonic
                 ) -> None:
        self.settings = settings
        self.clock = clock
        self.limit = settings.max_connections
        self.backlog = settings.backlog
        self._conns: OrderedDict[Any, _Conn] = OrderedDict()   # least recently active first
        self._per_peer: Counter[str] = Counter()
        self.evicted = self.refused = self.timed_out = 0
        self.most = 0   # most connections open at once

    def plan(self, soft: int | None = None, in_use: int | None = None) -> str | None:
        """Fit :attr:`limit` and :attr:`backlog` to the descriptors this process may still
        open: ``RLIMIT_NOFILE`` less those open now and ``fd_reserve``; the event loop accepts
        up to a backlog's worth in one go before the guard sees them, so the backlog is kept
        within a quarter of that room and the connections within the rest. Returns a note when
        the limit is below ``max_connections`` (None otherwise). ``soft`` / ``in_use``: the
        descriptor limit and the descriptors open (default: this process's)."""
        s = self.settings
        if soft is None:
            try:
                import resource

                soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
                if soft == resource.RLIM_INFINITY:
                    return None
            except (ImportError, OSError, ValueError):
                return None
        if soft <= 0:
            return None
        if in_use is None:
            try:
                in_use = len(os.listdir("/proc/self/fd"))
            except OSError:
                in_use = 32
        room = max(0, soft - in_use - s.fd_reserve)
        self.backlog = max(8, min(s.backlog, room // 4))
        self.limit = max(8, min(s.max_connections, room - self.backlog))
        if self.limit < s.max_connections:
            return (f"connections capped at {self.limit} (not server.max_connections "
                    f"{s.max_connections}): {soft} file descriptors allowed, {in_use} open, "
                    f"{s.fd_reserve} kept free, {self.backlog} for accepting")
        return None

    def attach(self, server: web.Server) -> None:
        """Follow ``server``'s connections (its ``connection_made`` / ``connection_lost``,
        which every aiohttp request handler calls on its manager)."""
        made, lost = server.connection_made, server.connection_lost

        def on_made(handler: Any, transport: Any) -> None:
            made(handler, transport)
            self.opened(handler, transport)

        def on_lost(handler: Any, exc: BaseException | None = None) -> None:
            self.closed(handler)
            lost(handler, exc)

        setattr(server, "connection_made", on_made)  # noqa: B010 - an instance's hook
        setattr(server, "connection_lost", on_lost)  # noqa: B010

    def __len__(self) -> int:
        return len(self._conns)

    def per_client(self, peer: str) -> int:
        return self._per_peer.get(peer, 0)

    def opened(self, handler: Any, transport: Any) -> None:
        peer = _peer(transport)
        full = ((self._per_peer[peer] >= self.settings.max_connections_per_client
                 and not self._evict(peer))
                or (len(self._conns) >= self.limit and not self._evict(None)))
        if full:   # every connection is answering a request: this one waits its turn outside
            self.refused += 1
            transport.abort()
            return
        self._conns[handler] = _Conn(transport, peer, self.clock())
        self._per_peer[peer] += 1
        self.most = max(self.most, len(self._conns))

    def _drop(self, handler: Any) -> _Conn | None:
        c = self._conns.pop(handler, None)
        if c is not None:
            self._per_peer[c.peer] -= 1
            if self._per_peer[c.peer] <= 0:
                del self._per_peer[c.peer]
        return c

    def _evict(self, peer: str | None) -> bool:
        """Close the oldest idle connection (of ``peer``; None: of anyone); False if none."""
        for h, c in self._conns.items():
            if c.busy == 0 and (peer is None or c.peer == peer):
                self._drop(h)
                self.evicted += 1
                c.transport.abort()
                return True
        return False

    def closed(self, handler: Any) -> None:
        self._drop(handler)

    def busy(self, handler: Any) -> None:
        """A request on ``handler``'s connection is being answered."""
        c = self._conns.get(handler)
        if c is not None:
            c.busy += 1

    def idle(self, handler: Any) -> None:
        """A request on ``handler``'s connection has been answered."""
        c = self._conns.get(handler)
        if c is not None:
            c.busy = max(0, c.busy - 1)
            if not c.busy:
                c.idle_since = self.clock()
                self._conns.move_to_end(handler)

    def sweep(self) -> int:
        """Close the connections idle longer than ``idle_timeout_s``; how many."""
        cutoff = self.clock() - self.settings.idle_timeout_s
        stale = [h for h, c in self._conns.items() if not c.busy and c.idle_since < cutoff]
        for h in stale:
            c = self._drop(h)
            if c is not None:
                c.transport.abort()
        self.timed_out += len(stale)
        return len(stale)


def _clip(text: object, n: int = 160) -> str:
    """``text`` on one line, control characters escaped, at most ``n`` characters (a log line
    quoting what a client sent)."""
    one = " ".join(str(text).split())
    one = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in one)
    return one if len(one) <= n else one[:n - 3] + "..."


class BadRequestLog(logging.Filter):
    """One line per malformed request, at most ``per_min`` a minute (aiohttp logs each with
    an 11-line traceback: 16 MB of log in 10 s from one client, issue 36).

    Installed on aiohttp's server logger and asyncio's (:meth:`install`): a record of a
    request aiohttp could not parse (``HttpProcessingError``: a bad request line, header,
    method, a line too long) becomes ``console: malformed request from ADDR answered 400
    (BadStatusLine: ...)``, without the traceback; asyncio's "socket.accept() out of system
    resource" becomes one line too. Past ``per_min`` in a minute they are counted, not
    logged, and the next line logged says how many were left out. Anything else passes as
    it is."""

    LOGGERS = ("aiohttp.server", "asyncio")

    def __init__(self, per_min: int, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.per_min = per_min
        self.clock = clock
        self.logged = self.suppressed = 0
        self._window, self._in_window, self._untold = -math.inf, 0, 0

    def line(self, record: logging.LogRecord) -> str | None:
        """The one line for ``record``, or None when it is not one this filter shortens."""
        exc = record.exc_info[1] if record.exc_info else None
        if record.name == "aiohttp.server" and isinstance(exc, http_exceptions.HttpProcessingError):
            args = record.args if isinstance(record.args, tuple) else ()
            who = _clip(args[0], 60) if args else "a client"
            return (f"console: malformed request from {who} answered 400 "
                    f"({type(exc).__name__}: {_clip(exc.message)})")
        msg = str(record.msg)
        if record.name == "asyncio" and msg.startswith("socket.accept() out of system"):
            why = _clip(exc, 80) if exc is not None else "out of system resource"
            return (f"console: a connection could not be accepted ({why}); accepting again "
                    "in 1 s")
        return None

    def filter(self, record: logging.LogRecord) -> bool:
        text = self.line(record)
        if text is None:
            return True
        now = self.clock()
        if now - self._window >= 60.0:
            self._window, self._in_window = now, 0
        if self._in_window >= self.per_min:
            self.suppressed += 1
            self._untold += 1
            return False
        self._in_window += 1
        self.logged += 1
        if self._untold:
            text += f" ({self._untold} more since the last line, not logged)"
            self._untold = 0
        record.msg, record.args = text, ()
        record.exc_info = record.exc_text = record.stack_info = None
        record.levelno, record.levelname = logging.WARNING, "WARNING"
        return True

    def install(self) -> None:
        for name in self.LOGGERS:
            logging.getLogger(name).addFilter(self)

    def remove(self) -> None:
        for name in self.LOGGERS:
            logging.getLogger(name).removeFilter(self)


class ConsoleServer:
    """HTTP + WebSocket front of a :class:`WeldSession`.

    Args:
        cfg: console settings.
        session: the weld.
        validate: turns the page's parameter form into :class:`WeldParams` (raises
            :class:`ParamError` with the operator's message).
        defaults: the form's initial values; ``choices``: lists for its selectors (noise
            names, faults, trackers, segment letters); ``source``: what feeds the loop, shown.
        token: the per-run token (default: a new ``secrets.token_urlsafe(32)``; tests pass a
            known one). ``allowed_hosts``: ``Host`` names to answer besides loopback and the
            bound address (a name the operator reaches a ``--host 0.0.0.0`` console by).
        extra_limits: ranges of form fields beyond ``cfg.limits`` (the simulated cell's start
            offset and angle off the seam), sent to the page with the others.
    """

    def __init__(self, cfg: ConsoleConfig, session: WeldSession,
                 validate: Callable[[dict[str, Any]], WeldParams], defaults: dict[str, Any],
                 choices: dict[str, Any], source: str = "simulated cell",
                 token: str | None = None, allowed_hosts: Iterable[str] = (),
                 extra_limits: dict[str, list[float]] | None = None) -> None:
        self.cfg = cfg
        #: The per-run secret every state-changing request and the WebSocket must carry.
        self.token = token or secrets.token_urlsafe(32)
        #: Host names answered besides loopback and the bound address (``--allow-host``).
        self.allowed_hosts = tuple(allowed_hosts)
        self.bind_host: str | None = None
        self.session = session
        self.validate = validate
        self.defaults = defaults
        self.choices = choices
        self.extra_limits = dict(extra_limits or {})
        self.source = source
        self.clients: set[_Client] = set()
        self.jpeg: _Jpeg | None = None
        self.jpeg_count = 0
        self.dropped_clients = 0
        self._status: dict[str, Any] = {}
        self._link: dict[str, Any] = {"connected": False}
        self._link_prev: tuple[Any, int, float, float] | None = None
        self._updates: dict[Cursor, tuple[str, Cursor]] = {}
        self._encoder = concurrent.futures.ThreadPoolExecutor(1, "torchseam-jpeg")
        self._publisher: asyncio.Task | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        # the publisher waits for the weld's next frame before each tick (see _publish)
        self._frame_done: asyncio.Event | None = None
        self._want_frame = False
        self.address: tuple[str, int] | None = None
        #: the page and its Content-Security-Policy (its inline code by hash), read once
        self.page_html = resources.files("torchseam.console").joinpath(
            "static/console.html").read_text()
        self.page_csp = page_csp(self.page_html, cfg.server.page_allows_eval)
        #: connection caps and idle timeout: the operator's path (:class:`ConnectionGuard`)
        self.guard = ConnectionGuard(cfg.server)
        #: malformed requests as one line each, rate-limited (:class:`BadRequestLog`)
        self.bad_request_log = BadRequestLog(cfg.server.bad_requests_logged_per_min)
        self._sweeper: asyncio.Task | None = None

    # ------------------------------------------------------------------ app
    def app(self) -> web.Application:
        timeout = self.cfg.server.request_timeout_s

        @web.middleware
        async def answering(request: web.Request, handler: Any) -> web.StreamResponse:
            """Mark the connection busy while its request is answered (an idle one may be
            closed to make room), and bound the answer's time (the stream excepted)."""
            conn = request.protocol
            self.guard.busy(conn)
            try:
                if request.path == "/ws":
                    return await handler(request)
                return await asyncio.wait_for(handler(request), timeout)
            except asyncio.TimeoutError:
                return _error(408, f"console: no answer within {timeout:g} s (the request "
                                   "body came too slowly; server.request_timeout_s)")
            finally:
                self.guard.idle(conn)

        @web.middleware
        async def guard(request: web.Request, handler: Any) -> web.StreamResponse:
            refused = self.refusal(request)
            if refused is not None:
                return _error(403, refused)
            return await handler(request)

        async def secure(request: web.Request, response: web.StreamResponse) -> None:
            _secure(response.headers)

        app = web.Application(client_max_size=MAX_BODY, middlewares=[answering, guard])
        app.on_response_prepare.append(secure)
        app.router.add_get("/", self._page)
        app.router.add_get("/api/auth", self._auth)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/frame.jpg", self._frame)
        app.router.add_post("/api/start", self._start)
        for action in ("hold", "resume", "stop"):
            app.router.add_post(f"/api/{action}", self._action)
        return app

    async def start(self, host: str, port: int) -> tuple[str, int]:
        """Serve on ``host:port`` (port 0: any free port) from the running event loop."""
        self._loop = asyncio.get_running_loop()
        self.bind_host = host
        s = self.cfg.server
        app = self.app()
        # keepalive_timeout: aiohttp closes a connection idle that long (from its opening
        # too); the guard's sweep does the same whatever the aiohttp version
        self._runner = web.AppRunner(app, access_log=None, keepalive_timeout=s.idle_timeout_s,
                                     max_line_size=s.max_line_size,
                                     max_field_size=s.max_field_size)
        await self._runner.setup()
        server = self._runner.server
        assert server is not None
        note = self.guard.plan()
        if note is not None:
            self.session.log(note, level="warn")
        self.guard.attach(server)
        # every request a _SecureRequest: aiohttp's own 400s get the security headers too
        server.request_factory = functools.partial(app._make_request, _cls=_SecureRequest)
        self.bad_request_log.install()
        site = web.TCPSite(self._runner, host, port, backlog=self.guard.backlog)
        try:
            await site.start()
        except BaseException:
            self.bad_request_log.remove()
            raise
        self.address = tuple(self._runner.addresses[0][:2])  # the port, ephemeral or not
        self._publisher = asyncio.create_task(self._publish())
        self._sweeper = asyncio.create_task(self._sweep())
        return self.address

    async def _sweep(self) -> None:
        """Close idle connections (:meth:`ConnectionGuard.sweep`) a few times per timeout."""
        period = min(1.0, self.cfg.server.idle_timeout_s / 4)
        while True:
            await asyncio.sleep(period)
            self.guard.sweep()

    def url(self) -> str:
        """The page's address with the token (what the CLI prints), once serving: on the
        bound name (one the Host check answers to); a wildcard bind (``0.0.0.0``, ``::``) is
        shown as ``127.0.0.1``."""
        if self.address is None:
            raise RuntimeError("the console is not serving yet")
        host = self.bind_host or "0.0.0.0"
        if host in ("0.0.0.0", "::"):
            host = "127.0.0.1"
        return f"http://{_host_name(host)}:{self.address[1]}/?{TOKEN_PARAM}={self.token}"

    # ------------------------------------------------------------------ who may ask
    def host_names(self) -> set[str]:
        """Names this console answers to (with its port): loopback, the bound address and
        ``allowed_hosts``."""
        names = set(LOOPBACK_NAMES)
        for h in (self.bind_host, *self.allowed_hosts):
            if h:
                names.add(_host_name(h))
        return names

    def _port(self, request: web.Request) -> int | None:
        """The port the request came in on (a ``localhost`` bind to port 0 may listen on two:
        IPv4 and IPv6)."""
        sock = request.transport.get_extra_info("sockname") if request.transport else None
        if isinstance(sock, tuple) and len(sock) >= 2:
            return int(sock[1])
        return int(self.address[1]) if self.address is not None else None

    def _is_us(self, hp: tuple[str, int] | None, port: int | None) -> bool:
        return hp is not None and hp[1] == port and hp[0] in self.host_names()

    def token_ok(self, request: web.Request, query: bool = False) -> bool:
        """The request carries this run's token (``X-Torchseam-Token``; ``?token=`` too when
        ``query``), compared in constant time."""
        given = request.headers.get(TOKEN_HEADER)
        if given is None and query:
            given = request.query.get(TOKEN_PARAM)
        if not given:
            return False
        return hmac.compare_digest(given.encode("utf-8", "surrogateescape"),
                                   self.token.encode("utf-8"))

    def refusal(self, request: web.Request) -> str | None:
        """Why ``request`` is refused (403), or None. The ``Host`` must name this console
        (a DNS-rebinding page carries its own name), an ``Origin`` the same, and all but the
        token-free reads (:data:`TOKEN_FREE`) the token."""
        port = self._port(request)
        host = request.headers.get("Host")
        if host is None or not self._is_us(split_host(host), port):
            shown = host[:100] if host else host
            return (f"console: Host {shown!r} is not this console (open it as "
                    f"http://127.0.0.1:{port}/, or start it with --allow-host NAME)")
        origin = request.headers.get("Origin")
        if origin is not None:
            try:
                o = urlsplit(origin) if len(origin) < 300 else None
            except ValueError:  # "http://[::1": not a URL
                o = None
            hp = (split_host(o.netloc, 443 if o.scheme == "https" else 80)
                  if o is not None and o.scheme in ("http", "https") and o.netloc
                  and not o.path.strip("/") and not o.query else None)
            if not self._is_us(hp, port):
                return f"console: requests from {origin[:100]} are not accepted"
        if request.method in ("GET", "HEAD") and request.path in TOKEN_FREE:
            return None
        if not self.token_ok(request, query=request.method == "GET"
                             and request.path == "/ws"):
            given = (request.headers.get(TOKEN_HEADER) is not None
                     or TOKEN_PARAM in request.query)
            return ("console: wrong token" if given else
                    f"console: this request needs the console's token ({TOKEN_HEADER} "
                    "header; the page takes it from the ?token=... address the console "
                    "printed at start)")
        return None

    async def close(self) -> None:
        self.session.frame_done = None
        if self._publisher is not None:
            self._publisher.cancel()
        if self._sweeper is not None:
            self._sweeper.cancel()
        self.bad_request_log.remove()
        for c in list(self.clients):
            await c.ws.close()
        if self._runner is not None:
            await self._runner.cleanup()
        self._encoder.shutdown(wait=False)

    def start_in_thread(self, host: str, port: int) -> tuple[str, int]:
        """Run the server on an event loop of its own thread (tests, benchmarks)."""
        ready = threading.Event()
        box: dict[str, Any] = {}

        def main() -> None:
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            try:
                box["addr"] = loop.run_until_complete(self.start(host, port))
            except BaseException as e:  # noqa: BLE001 - handed to the caller
                box["err"] = e
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.run_until_complete(self.close())
            pending = asyncio.all_tasks(loop)
            for t in pending:
                t.cancel()
            loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            loop.close()

        self._thread = threading.Thread(target=main, name="torchseam-console", daemon=True)
        self._thread.start()
        ready.wait()
        if "err" in box:
            raise box["err"]
        return box["addr"]

    def stop_thread(self) -> None:
        if self._loop is not None and self._thread is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)

    # ------------------------------------------------------------------ publisher
    def _on_frame_done(self) -> None:
        """Weld thread, after each frame's record is stored: wake a publisher waiting for it
        (a flag test per frame otherwise)."""
        if self._want_frame and self._loop is not None and self._frame_done is not None:
            self._want_frame = False
            try:
                self._loop.call_soon_threadsafe(self._frame_done.set)
            except RuntimeError:
                pass  # the server closed its loop meanwhile: the weld goes on without it

    async def _after_next_frame(self, timeout: float) -> None:
        """Wait until the weld has handed over its next frame (at most ``timeout``). The
        publisher's work (status, JSON, sends) holds the interpreter lock for a few ms a tick;
        started right after a frame, it falls in the gap before the next one instead of
        stalling a frame half-way, the loop waiting for the lock (docs/console.md)."""
        ev = self._frame_done
        if ev is None or not self.session.running:
            return
        ev.clear()
        self._want_frame = True
        try:
            await asyncio.wait_for(ev.wait(), timeout)
        except asyncio.TimeoutError:
            pass  # held, stopped or slow: tick anyway
        finally:
            self._want_frame = False

    async def _publish(self) -> None:
        pub = self.cfg.publish
        loop = asyncio.get_running_loop()
        self._frame_done = asyncio.Event()
        self.session.frame_done = self._on_frame_done
        period = 1.0 / pub.rate_hz
        next_jpeg = next_link = 0.0
        next_tick = loop.time()
        while True:
            await self._after_next_frame(max(period, FRAME_WAIT_S))
            now = loop.time()
            # the next tick on the rate's own schedule (waiting for frames does not slow it)
            next_tick = max(next_tick + period, now)
            lf = self.session.latest
            if lf is not None and (self.jpeg is None or lf.seq != self.jpeg.seq) \
                    and now >= next_jpeg:
                # on the rate's schedule: ticks come up to a frame late, and a deadline from
                # ``now`` would skip every other frame at jpeg_rate_hz == rate_hz
                next_jpeg = max(next_jpeg + 1.0 / pub.jpeg_rate_hz, now - 0.5 / pub.rate_hz)
                try:
                    data = await loop.run_in_executor(self._encoder, render_frame, lf,
                                                      pub.jpeg_scale, pub.jpeg_quality)
                    self.jpeg = _Jpeg(lf.seq, data)
                    self.jpeg_count += 1
                except Exception as e:  # noqa: BLE001 - a bad frame must not end the stream
                    self.session.log(f"frame not shown: {e}", level="error")
            if now >= next_link:
                next_link = max(next_link + 1.0 / pub.link_stats_hz, now - 0.5 / pub.rate_hz)
                self._link = self._link_state()
            self._status = self.session.status()
            self._status["link"] = self._link
            self._status["clients"] = len(self.clients)
            self._updates = {}
            for c in self.clients:
                c.wake.set()
            await asyncio.sleep(max(0.0, next_tick - loop.time()))

    def _link_state(self) -> dict[str, Any]:
        """The EGM link's state from its (locked) counters, with cycle rates."""
        link = self.session.link
        if link is None:
            return {"connected": False}
        if not hasattr(link, "stats") or not hasattr(link, "holding"):
            # a replay's pose sink (open loop): poses are kept, nothing reaches a robot
            return {"connected": False, "note": NO_CONTROLLER,
                    "sink_accepted": getattr(link, "accepted", None),
                    "sink_refused": getattr(link, "refused", None)}
        st = link.stats
        lf = self.session.latest
        t_link = lf.t_s if lf is not None else math.nan
        wall = time.perf_counter()
        rate = wall_rate = math.nan
        advanced = False
        if self._link_prev is not None:
            prev_link, n0, t0, w0 = self._link_prev
            dn = st.received - n0 if prev_link is link else st.received
            advanced = dn > 0
            if prev_link is link and t_link > t0:
                rate = dn / (t_link - t0)
            if wall > w0:
                wall_rate = dn / (wall - w0)
        self._link_prev = (link, st.received, t_link, wall)
        ctl = self.session.control
        running = self.session.running and not (ctl is not None and ctl.held)
        return {"connected": bool(st.received > 0 and (advanced or not running)
                                  and not link.holding),
                "watchdog_holding": bool(link.holding), "received": st.received,
                "sent": st.sent, "commands": st.commands,
                "cycle_rate_hz": num(rate, 1), "wall_rate_hz": num(wall_rate, 1),
                "refused": dict(st.refused), "holds": dict(st.holds),
                "dropped": dict(st.dropped), "late_replies": st.late_replies,
                "controller_silences": st.controller_silences,
                "watchdog_trips": st.watchdog_trips}

    # ------------------------------------------------------------------ streams
    def hello(self) -> tuple[dict[str, Any], Any]:
        """Settings, form defaults and the full history (what a new tab starts from), and the
        cursor of that history."""
        data, cursor = self.session.delta(None)
        status = self.session.status()
        status["link"] = self._link
        status["clients"] = len(self.clients)
        return {"type": "hello", "source": self.source, "defaults": self.defaults,
                "choices": self.choices, "limits": {**_limits(self.cfg), **self.extra_limits},
                "history": {"frames": self.cfg.history.frames,
                            "commands": self.cfg.history.commands,
                            "messages": self.cfg.history.messages},
                "status": status, **data}, cursor

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        if len(self.clients) >= self.cfg.server.max_clients:
            raise web.HTTPServiceUnavailable(
                text=f"console: {self.cfg.server.max_clients} clients already connected")
        ws = web.WebSocketResponse(heartbeat=self.cfg.server.heartbeat_s)
        await ws.prepare(request)
        client = _Client(ws)
        self.clients.add(client)
        sender = asyncio.create_task(self._sender(client))
        try:
            async for msg in ws:  # the page sends nothing; control goes through /api
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.clients.discard(client)
            sender.cancel()
        return ws

    async def _sender(self, client: _Client) -> None:
        timeout = self.cfg.server.send_timeout_s
        ws = client.ws
        try:
            snap, cursor = self.hello()
            await asyncio.wait_for(ws.send_str(json.dumps(snap)), timeout)
            while not ws.closed:
                jpeg = self.jpeg
                if jpeg is not None and jpeg.seq != client.jpeg_seq:
                    await asyncio.wait_for(ws.send_bytes(jpeg.data), timeout)
                    client.jpeg_seq = jpeg.seq
                await client.wake.wait()
                client.wake.clear()
                text, cursor = self._update_for(cursor)
                await asyncio.wait_for(ws.send_str(text), timeout)
                client.sent += 1
        except (asyncio.TimeoutError, ConnectionResetError):
            self.dropped_clients += 1
            self.session.log("a console client was too slow and was disconnected",
                             level="warn")
            self.clients.discard(client)
            await ws.close()

    def _update_for(self, cursor: Cursor) -> tuple[str, Cursor]:
        """The ``update`` message for a client at ``cursor``, built once per publisher tick for
        all clients at the same cursor (they usually are)."""
        hit = self._updates.get(cursor)
        if hit is None:
            data, new = self.session.delta(cursor)
            hit = (json.dumps({"type": "update", "status": self._status, **data}), new)
            self._updates[cursor] = hit
        return hit

    # ------------------------------------------------------------------ HTTP
    async def _page(self, request: web.Request) -> web.Response:
        return web.Response(text=self.page_html, content_type="text/html",
                            headers={"Cache-Control": "no-store",
                                     "Content-Security-Policy": self.page_csp})

    async def _auth(self, request: web.Request) -> web.Response:
        return web.json_response({"ok": True})  # the guard has checked the token

    async def _state(self, request: web.Request) -> web.Response:
        return web.json_response(self.hello()[0])

    async def _frame(self, request: web.Request) -> web.Response:
        if self.jpeg is None:
            raise web.HTTPNotFound(text="no frame yet")
        return web.Response(body=self.jpeg.data, content_type="image/jpeg",
                            headers={"Cache-Control": "no-store"})

    async def _start(self, request: web.Request) -> web.Response:
        try:
            raw = parse_body(await request.read())
        except web.HTTPRequestEntityTooLarge:
            return _error(413, f"parameters: the request is larger than {MAX_BODY // 1024} KiB")
        except ValueError as e:
            self.session.log(f"start refused: {e}", level="warn")
            return _error(400, str(e))
        try:
            params = self.validate(raw)
        except ParamError as e:
            self.session.log(f"start refused: {e}", level="warn")
            return _error(400, str(e))
        except (TypeError, ValueError, OverflowError) as e:   # a check that missed a case
            msg = f"parameters: refused ({type(e).__name__}: {str(e)[:120]})"
            self.session.log(f"start refused: {msg}", level="warn")
            return _error(400, msg)
        try:
            self.session.start(params)
        except RuntimeError as e:
            return _error(409, str(e))
        return web.json_response({"ok": True, "params": params.as_dict()})

    async def _action(self, request: web.Request) -> web.Response:
        action = request.path.rsplit("/", 1)[-1]
        ctl = self.session.control
        if self.session.running and ctl is not None and not ctl.stopped:
            if action == "hold" and ctl.held:
                return _error(409, "hold: the weld is already held")
            if action == "resume" and not ctl.held:
                return _error(409, "resume: the weld is not held")
        try:
            getattr(self.session, action)()
        except RuntimeError as e:
            return _error(409, str(e))
        return web.json_response({"ok": True, "state": self.session.state})


def _error(status: int, text: str) -> web.Response:
    return web.json_response({"ok": False, "error": text}, status=status)


def _limits(cfg: ConsoleConfig) -> dict[str, list[float]]:
    lim = cfg.limits
    return {"step_mm": list(lim.step_mm), "look_ahead_mm": list(lim.look_ahead_mm),
            "weld_speed_mm_s": list(lim.weld_speed_mm_s), "length_mm": list(lim.length_mm),
            "seed": list(lim.seed)}
