"""The console keeps a path open for its operator (issue 36): with 1 024 file descriptors and
1 100 idle connections opened to it, ``/api/state`` and the operator's ``stop`` answer within
1 s; idle and slow-header connections are closed; a client's connections are capped, the
oldest idle one making way; a malformed request is one log line, rate-limited; every response
carries the security headers, and the page runs under its Content-Security-Policy.

Most tests run the console of ``tests/test_console.py`` (its fake weld) in a thread on an
ephemeral loopback port; the descriptor test runs ``torchseam console`` in a subprocess with
``RLIMIT_NOFILE`` 1024, its idle connections held by two helper processes.
"""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import hashlib
import http.client
import json
import logging
import re
import resource
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_console import GOOD, TOKEN, chromium, fake_console, wait_for  # noqa: F401 - fixture

from torchseam.console.config import ServerSettings, load_console_config
from torchseam.console.server import (
    CSP_STRICT,
    MAX_BODY,
    SECURITY_HEADERS,
    TOKEN_HEADER,
    BadRequestLog,
    ConnectionGuard,
    _InlineCode,
    page_csp,
)
from torchseam.core.config import CONFIG_DIR, ConfigError

pytestmark = pytest.mark.realtime  # wall-clock timing: run alone (README's test command)


def _cfg(**server):
    c = load_console_config()
    return dataclasses.replace(c, pace=0.0, server=dataclasses.replace(c.server, **server))


@pytest.fixture()
def served():
    made = []

    def make(**server):
        con = fake_console(_cfg(**server))
        host, port = con.start_in_thread("127.0.0.1", 0)
        made.append(con)
        return con, host, port

    yield make
    for con in made:
        if con.session.running:
            con.session.stop()
            con.session.join(10)
        con.stop_thread()


def _http(host: str, port: int, method: str, path: str, body: bytes | None = None,
          headers: dict | None = None, timeout: float = 10) -> tuple[int, dict, bytes]:
    c = http.client.HTTPConnection(host, port, timeout=timeout)
    try:
        c.request(method, path, body=body, headers={"Host": f"{host}:{port}", **(headers or {})})
        r = c.getresponse()
        return r.status, dict(r.getheaders()), r.read()
    finally:
        c.close()


def _raw(host: str, port: int, data: bytes, timeout: float = 5) -> bytes:
    """Send ``data`` on a new connection and read the answer until the server closes."""
    with socket.create_connection((host, port), timeout=timeout) as s:
        s.sendall(data)
        out = b""
        while True:
            b = s.recv(65536)
            if not b:
                return out
            out += b


def _closed_by_peer(s: socket.socket, within: float) -> bool:
    """True when the server closes ``s`` within ``within`` seconds."""
    s.settimeout(within)
    try:
        return s.recv(1) == b""
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


# --------------------------------------------------------------------------- security headers

def _has_headers(headers, csp: str | None = CSP_STRICT) -> None:
    for k, v in SECURITY_HEADERS.items():
        assert headers.get(k) == v, (k, headers)
    got = headers.get("Content-Security-Policy")
    assert got is not None and "frame-ancestors 'none'" in got, headers
    if csp is not None:
        assert got == csp


def test_every_response_carries_the_security_headers(served):
    con, host, port = served()
    status, h, body = _http(host, port, "GET", "/")
    assert status == 200 and b"<script>" in body
    _has_headers(h, csp=con.page_csp)
    for method, path, data, hdr, want in [
            ("GET", "/api/state", None, {}, 200),
            ("GET", "/frame.jpg", None, {}, 404),                       # no frame yet
            ("GET", "/nope", None, {}, 403),                            # no token
            ("GET", "/nope", None, {TOKEN_HEADER: TOKEN}, 404),
            ("GET", "/api/auth", None, {TOKEN_HEADER: "wrong"}, 403),
            ("POST", "/api/stop", b"{}", {TOKEN_HEADER: TOKEN}, 409),    # no weld runs
            ("POST", "/api/start", b"[[[", {TOKEN_HEADER: TOKEN}, 400),
            ("POST", "/api/start", b"x" * (MAX_BODY + 10), {TOKEN_HEADER: TOKEN}, 413),
            ("GET", "/", None, {"Host": "evil.example"}, 403)]:
        status, h, _ = _http(host, port, method, path, data, hdr)
        assert status == want, (method, path, status)
        _has_headers(h)
    # aiohttp's own 400 for a request it cannot parse (no middleware, no signal sees it)
    raw = _raw(host, port, b"GET / HTTP/9.9\r\nHost: x\r\n\r\n").decode("latin-1")
    assert raw.startswith("HTTP/1.0 400") or raw.startswith("HTTP/1.1 400"), raw[:80]
    head = dict(line.split(": ", 1) for line in raw.split("\r\n\r\n")[0].split("\r\n")[1:])
    _has_headers(head)

    async def ws_headers() -> dict:
        async with aiohttp.ClientSession() as s, \
                s.ws_connect(f"ws://{host}:{port}/ws?token={TOKEN}") as ws:
            await ws.receive(timeout=10)
            return dict(ws._response.headers)

    _has_headers(asyncio.run(ws_headers()))


def _hash(text: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"


def test_the_page_csp_lists_exactly_the_page_inline_code(served):
    con, _, _ = served()
    found = _InlineCode()
    found.feed(con.page_html)
    csp = dict(d.strip().split(" ", 1) for d in con.page_csp.split(";"))
    assert csp["default-src"] == "'none'" and csp["frame-ancestors"] == "'none'"
    assert csp["img-src"] == "'self' blob:" and csp["connect-src"] == "'self'"
    script, style = set(csp["script-src"].split()), set(csp["style-src"].split())
    assert found.scripts and found.styles and found.handlers and found.style_attrs
    assert script - {"'unsafe-hashes'", "'unsafe-eval'"} == {
        _hash(t) for t in found.scripts + found.handlers}
    assert style - {"'unsafe-hashes'"} == {_hash(t) for t in found.styles + found.style_attrs}
    assert "'unsafe-inline'" not in con.page_csp
    strict = page_csp(con.page_html)
    assert "'unsafe-eval'" not in strict and strict.replace(" 'unsafe-eval'", "") == strict
    with pytest.raises(ValueError, match="self-contained"):
        page_csp("<script src='https://cdn.example/x.js'></script>")


@settings(max_examples=60, deadline=None)
@given(scripts=st.lists(st.text(alphabet="ab;(){}= \n'\"<>&", max_size=30), max_size=3),
       handlers=st.lists(st.text(alphabet="ab;()= &", min_size=1, max_size=20), max_size=3),
       injected=st.text(alphabet="xyz();", min_size=1, max_size=20))
def test_csp_hashes_allow_the_page_code_and_nothing_injected(scripts, handlers, injected):
    scripts = [s.replace("</", "<\\/") for s in scripts]
    body = "".join(f"<script>{s}</script>" for s in scripts)
    body += "".join(f"<button onclick=\"{h.replace('&', '&amp;')}\">b</button>"
                    for h in handlers)
    csp = page_csp(f"<html><head></head><body>{body}</body></html>")
    src = csp.split("script-src ", 1)[1].split(";", 1)[0].split()
    for s in scripts:
        assert _hash(s) in src
    for h in handlers:
        assert _hash(h) in src and "'unsafe-hashes'" in src
    if injected not in scripts and injected not in handlers:
        assert _hash(injected) not in src
    if not scripts and not handlers:
        assert src == ["'none'"]


def test_the_page_runs_under_its_strictest_csp_and_cannot_be_framed(chromium, served):  # noqa: F811
    """The page's own code runs under the policy without 'unsafe-eval' (polled from Python:
    Playwright's wait_for_function evaluates in the page); an injected handler does not; a
    page framing the console gets nothing."""
    from playwright.sync_api import sync_playwright

    con, host, port = served(page_allows_eval=False)
    assert "'unsafe-eval'" not in con.page_csp
    messages: list[tuple[str, str]] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(chromium), headless=True)
        try:
            page = browser.new_page()
            page.on("console", lambda m: messages.append((m.type, m.text)))
            page.goto(f"http://{host}:{port}/?token={TOKEN}")

            def poll(expr: str, timeout: float = 30) -> None:
                t0 = time.monotonic()
                while not page.evaluate(expr):
                    assert time.monotonic() - t0 < timeout, expr
                    time.sleep(0.1)

            poll("document.querySelector('#run-state').dataset.state === 'idle'")
            page.click("#btn-start")   # the form's inline handlers and the fetch run
            poll("+document.querySelector('#frames-shown').textContent > 2")   # the stream
            poll("+document.querySelector('#plot-uv').dataset.points > 2")
            assert page.evaluate("document.querySelector('#frame').src").startswith("blob:")
            page.evaluate("document.body.insertAdjacentHTML('beforeend', "
                          "'<img src=x onerror=\"window.__injected = 1\">')")
            time.sleep(0.5)
            assert page.evaluate("window.__injected") is None
            page.click("#btn-stop")
            poll("['stopped', 'finished'].includes("
                 "document.querySelector('#run-state').dataset.state)")
            blocked = [t for k, t in messages if "Content Security Policy" in t]
            assert len(blocked) == 1 and "inline event handler" in blocked[0], messages
            # framed by another page: the browser shows an error page in the frame instead
            page.goto("about:blank")
            page.set_content(f"<iframe src='http://{host}:{port}/'></iframe>")
            time.sleep(1.5)
            inner = [f for f in page.frames if f != page.main_frame]
            assert inner and not inner[0].url.startswith(f"http://{host}:{port}"), \
                [f.url for f in inner]
        finally:
            browser.close()


# --------------------------------------------------------------------------- malformed requests

MALFORMED = [b"GET / HTTP/9.9", b"GET / HTTP/1.1 x", b"GET /\x1b[31m HTTP/1.1",
             b"GET / XTTP/1.1"]


def test_a_malformed_request_line_is_one_log_line(served, caplog):
    con, host, port = served()
    caplog.set_level(logging.DEBUG, logger="aiohttp.server")
    for line in MALFORMED:
        caplog.clear()
        raw = _raw(host, port, line + b"\r\nHost: x\r\n\r\n")
        assert b" 400 " in raw.split(b"\r\n", 1)[0]
        wait_for(lambda: caplog.records, timeout=5, what="the log line")
        time.sleep(0.1)
        recs = [r for r in caplog.records if r.name == "aiohttp.server"]
        assert len(recs) == 1, [r.getMessage() for r in recs]
        text = recs[0].getMessage()
        assert recs[0].exc_info is None and "\n" not in text and "\x1b" not in text
        assert text.startswith("console: malformed request from 127.0.0.1 answered 400 ("), text
        assert len(text) < 260
    assert con.bad_request_log.logged == len(MALFORMED)


def test_malformed_requests_are_rate_limited(served, caplog):
    con, host, port = served(bad_requests_logged_per_min=5)
    caplog.set_level(logging.DEBUG, logger="aiohttp.server")
    for _ in range(60):
        _raw(host, port, b"GET / HTTP/9.9\r\nHost: x\r\n\r\n")
    wait_for(lambda: con.bad_request_log.logged + con.bad_request_log.suppressed >= 60,
             timeout=10, what="60 malformed requests")
    lines = [r.getMessage() for r in caplog.records if r.name == "aiohttp.server"]
    assert len(lines) == 5 and con.bad_request_log.suppressed == 55
    # the traceback-free line, never the 11-line traceback
    assert not any(r.exc_info for r in caplog.records)
    # the next line after the minute says how many were left out
    con.bad_request_log._window -= 61
    _raw(host, port, b"GET / HTTP/9.9\r\nHost: x\r\n\r\n")
    wait_for(lambda: con.bad_request_log.logged == 6, timeout=5, what="the next line")
    assert "(55 more since the last line, not logged)" in caplog.records[-1].getMessage()


@settings(max_examples=200, deadline=None)
@given(per_min=st.integers(0, 8), gaps=st.lists(st.floats(0, 40), min_size=1, max_size=80))
def test_the_rate_limit_holds_for_any_arrivals(per_min, gaps):
    now = [0.0]
    f = BadRequestLog(per_min, clock=lambda: now[0])
    told = 0
    emitted: list[float] = []
    for g in gaps:
        now[0] += g
        rec = logging.LogRecord("aiohttp.server", logging.ERROR, __file__, 1,
                                "Error handling request from %s", ("10.0.0.1",),
                                (None, _bad(), None))
        if f.filter(rec):
            emitted.append(now[0])
            assert rec.exc_info is None and "\n" not in rec.getMessage()
            m = re.search(r"\((\d+) more since the last line", rec.getMessage())
            told += int(m.group(1)) if m else 0
    assert f.logged == len(emitted) and f.logged + f.suppressed == len(gaps)
    assert told <= f.suppressed and f.suppressed - told == f._untold
    for t in emitted:   # never more than per_min lines in any window the filter opened
        assert sum(t <= u < t + 60 for u in emitted) <= max(per_min, 0) * 2


def _bad():
    from aiohttp import http_exceptions

    return http_exceptions.BadStatusLine("GET / HTTP/9.9\n\n  ^")


def test_other_errors_keep_their_traceback():
    f = BadRequestLog(1)
    rec = logging.LogRecord("aiohttp.server", logging.ERROR, __file__, 1, "Unhandled exception",
                            (), (ValueError, ValueError("bug"), None))
    assert f.filter(rec) and rec.exc_info is not None   # a bug is not a bad request


# --------------------------------------------------------------------------- idle connections

def test_silent_and_slow_header_connections_are_closed(served):
    con, host, port = served(idle_timeout_s=0.5)
    silent = socket.create_connection((host, port))
    slow = socket.create_connection((host, port))
    slow.sendall(b"GET /api/state HTTP/1.1\r\n")
    t0 = time.monotonic()
    for _ in range(6):   # a header byte every 0.2 s: never complete
        try:
            slow.sendall(b"X")
        except OSError:   # closed already
            break
        time.sleep(0.2)
    assert _closed_by_peer(silent, 1.0)
    assert _closed_by_peer(slow, 1.0)
    assert time.monotonic() - t0 < 3.0
    # a keep-alive connection left idle after its request
    keep = http.client.HTTPConnection(host, port, timeout=5)
    keep.request("GET", "/api/state", headers={"Host": f"{host}:{port}"})
    assert keep.getresponse().read() and keep.sock is not None
    assert _closed_by_peer(keep.sock, 2.0)
    keep.close()
    silent.close()
    slow.close()
    wait_for(lambda: len(con.guard) == 0, timeout=5, what="no connection left")


def test_a_request_whose_body_never_comes_gets_408(served):
    con, host, port = served(request_timeout_s=0.5, idle_timeout_s=30)
    with socket.create_connection((host, port), timeout=5) as s:
        s.sendall(f"POST /api/start HTTP/1.1\r\nHost: {host}:{port}\r\n{TOKEN_HEADER}: {TOKEN}"
                  f"\r\nContent-Type: application/json\r\nContent-Length: 200\r\n\r\n{{"
                  .encode())
        t0 = time.monotonic()
        answer = s.recv(4096)
        assert time.monotonic() - t0 < 3.0
    assert answer.startswith(b"HTTP/1.1 408"), answer[:60]
    assert b"request_timeout_s" in answer
    assert not con.session.running


def test_one_client_cannot_hold_more_than_its_share(served):
    """Past ``max_connections_per_client``, each new connection closes that address's oldest
    idle one: a request made after 40 idle connections is answered at once."""
    con, host, port = served(max_connections=32, max_connections_per_client=16,
                             idle_timeout_s=60)
    socks = [socket.create_connection((host, port)) for _ in range(40)]
    wait_for(lambda: con.guard.evicted >= 24, timeout=5, what="24 evictions")
    assert con.guard.per_client("127.0.0.1") <= 16 and con.guard.most <= 16
    assert all(_closed_by_peer(s, 1.0) for s in socks[:24])
    assert not any(_closed_by_peer(s, 0.01) for s in socks[-15:])
    t0 = time.monotonic()
    status, _, _ = _http(host, port, "GET", "/api/state")
    assert status == 200 and time.monotonic() - t0 < 1.0
    for s in socks:
        s.close()


def test_the_total_cap_across_addresses(served):
    """Three loopback addresses (127.0.0.1..3), each under its own cap: the total stays at
    ``max_connections``, the oldest idle connection of anyone making way."""
    con, host, port = served(max_connections=16, max_connections_per_client=12,
                             idle_timeout_s=60)
    socks = []
    for k in range(36):
        s = socket.socket()
        s.bind((f"127.0.0.{1 + k % 3}", 0))
        s.connect((host, port))
        socks.append(s)
    wait_for(lambda: con.guard.evicted >= 20, timeout=5, what="20 evictions")
    assert len(con.guard) <= 16 and con.guard.most <= 16
    assert all(_closed_by_peer(s, 1.0) for s in socks[:20])
    assert _http(host, port, "GET", "/api/state")[0] == 200
    for s in socks:
        s.close()


def test_a_page_stream_is_never_closed_to_make_room(served):
    con, host, port = served(max_connections=32, max_connections_per_client=16,
                             idle_timeout_s=0.5)

    async def watch() -> int:
        async with aiohttp.ClientSession() as s, \
                s.ws_connect(f"ws://{host}:{port}/ws?token={TOKEN}") as ws:
            assert json.loads((await ws.receive(timeout=10)).data)["type"] == "hello"
            flood = [socket.create_connection((host, port)) for _ in range(40)]
            await asyncio.sleep(1.5)   # past the idle timeout too
            got = 0
            for _ in range(3):
                msg = await ws.receive(timeout=5)
                got += msg.type == aiohttp.WSMsgType.TEXT
            for f in flood:
                f.close()
            return got

    assert asyncio.run(watch()) == 3
    assert con.guard.refused == 0 and con.guard.evicted >= 24


# --------------------------------------------------------------------------- the guard itself

class _Transport:
    def __init__(self, peer: str) -> None:
        self.peer, self.aborted = peer, False

    def get_extra_info(self, name: str):
        return (self.peer, 1234) if name == "peername" else None

    def abort(self) -> None:
        self.aborted = True


OPS = st.lists(st.one_of(
    st.tuples(st.just("open"), st.sampled_from(["a", "b", "c"])),
    st.tuples(st.sampled_from(["close", "busy", "idle"]), st.integers(0, 60)),
    st.tuples(st.just("tick"), st.floats(0, 3))), max_size=120)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=OPS, limit=st.integers(2, 10), per=st.integers(2, 10))
def test_the_guard_keeps_its_caps_and_never_closes_a_busy_connection(ops, limit, per):
    per = min(per, limit)
    now = [0.0]
    s = dataclasses.replace(load_console_config().server, max_connections=limit,
                            max_connections_per_client=per, max_clients=1, idle_timeout_s=2.0)
    g = ConnectionGuard(s, clock=lambda: now[0])
    conns: list[tuple[object, _Transport]] = []
    busy: dict[int, int] = {}
    for op, arg in ops:
        if op == "open":
            h, t = object(), _Transport(arg)
            scope_full = (g.per_client(arg) >= per, len(g) >= limit)
            idle_peer = any(not busy.get(id(hh)) and not tt.aborted and tt.peer == arg
                            for hh, tt in conns)
            idle_any = any(not busy.get(id(hh)) and not tt.aborted for hh, tt in conns)
            g.opened(h, t)
            conns.append((h, t))
            refused = t.aborted
            # refused only when its scope was full and nothing there could make way
            if refused:
                assert (scope_full[0] and not idle_peer) or (scope_full[1] and not idle_any)
        elif op == "tick":
            now[0] += arg
            g.sweep()
            for hh, tt in conns:   # nothing idle past the timeout is left open
                if not tt.aborted and not busy.get(id(hh)):
                    assert g._conns[hh].idle_since >= now[0] - s.idle_timeout_s
        elif conns:
            h, t = conns[arg % len(conns)]
            if t.aborted:
                continue
            if op == "close":
                g.closed(h)
                t.aborted = True   # the peer went: as gone as an aborted one
                busy.pop(id(h), None)
            elif op == "busy":
                g.busy(h)
                busy[id(h)] = busy.get(id(h), 0) + 1
            elif busy.get(id(h)):
                g.idle(h)
                busy[id(h)] -= 1
        assert len(g) <= limit
        assert all(g.per_client(p) <= per for p in "abc")
        for hh, tt in conns:   # a connection answering a request is never closed
            if busy.get(id(hh)):
                assert not tt.aborted and hh in g._conns


def test_the_connection_cap_follows_the_descriptor_limit():
    s = load_console_config().server
    g = ConnectionGuard(s)
    assert g.plan(soft=1024, in_use=40) is None   # room 920: backlog 230, 256 connections
    assert (g.limit, g.backlog) == (256, 230)
    note = ConnectionGuard(s).plan(soft=300, in_use=40)
    assert note is not None and "connections capped at 147" in note
    g = ConnectionGuard(s)
    g.plan(soft=64, in_use=60)
    assert g.limit == 8 and g.backlog == 8   # never below a working minimum


def test_connection_settings_are_checked(tmp_path):
    text = (CONFIG_DIR / "console.yaml").read_text()
    for old, new, message in [
            ("max_connections_per_client: 64", "max_connections_per_client: 300",
             r"server\.max_connections_per_client \(300\) above max_connections \(256\)"),
            ("max_clients: 8 ", "max_clients: 64 ", r"server\.max_clients \(64\) must be below"),
            ("idle_timeout_s: 10.0", "idle_timeout_s: 0", r"server\.idle_timeout_s: expected"),
            ("backlog: 512", "backlog: 0", r"server\.backlog: expected")]:
        assert old in text, old
        p = tmp_path / "console.yaml"
        p.write_text(text.replace(old, new, 1))
        with pytest.raises(ConfigError, match=message):
            load_console_config(p)
    # written before these settings existed: the defaults
    old_style = re.sub(r"\n  (max_connections|max_connections_per_client|idle_timeout_s|"
                       r"request_timeout_s|backlog|fd_reserve|max_line_size|max_field_size|"
                       r"bad_requests_logged_per_min|page_allows_eval):[^\n]*", "", text)
    p.write_text(old_style)
    assert load_console_config(p).server == ServerSettings(
        port=8642, max_clients=8, send_timeout_s=5.0, heartbeat_s=10.0)


# --------------------------------------------------------------------------- 1 024 descriptors

IDLE = 1100
NOFILE = 1024

_HOLD = r"""
import resource, socket, sys
host, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
if soft < n + 64:
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, n + 64), hard))
socks, failed = [], 0
for _ in range(n):
    try:
        socks.append(socket.create_connection((host, port), timeout=3))
    except OSError:
        failed += 1
print(f"opened {len(socks)} failed {failed}", flush=True)
sys.stdin.read()   # hold them until the test is done
"""


def _nofile() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (NOFILE, NOFILE))


def test_stop_answers_within_1s_with_1024_descriptors_and_1100_idle_connections(tmp_path):
    console = subprocess.Popen(
        [sys.executable, "-m", "torchseam", "console", "--port", "0", "--segments", "a"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_nofile)
    holders: list[subprocess.Popen] = []
    try:
        line = console.stdout.readline()
        m = re.search(r"http://127\.0\.0\.1:(\d+)/\?token=(\S+)", line)
        assert m, (line, console.poll())
        port, token = int(m.group(1)), m.group(2)

        def ask(method: str, path: str, body: dict | None = None) -> tuple[int, float, dict]:
            t0 = time.perf_counter()
            status, _, raw = _http("127.0.0.1", port, method, path,
                                   json.dumps(body).encode() if body is not None else None,
                                   {TOKEN_HEADER: token, "Content-Type": "application/json"},
                                   timeout=10)
            return status, time.perf_counter() - t0, json.loads(raw)

        weld = {**GOOD, "weld_speed_mm_s": 4, "length_mm": 80}   # 20 s: still running below
        assert ask("POST", "/api/start", weld)[0] == 200
        wait_for(lambda: ask("GET", "/api/state")[2]["status"]["state"] == "running",
                 timeout=30, what="the weld running")
        holders = [subprocess.Popen([sys.executable, "-c", _HOLD, "127.0.0.1", str(port),
                                     str(IDLE // 2)], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, text=True) for _ in range(2)]
        t0 = time.monotonic()
        opened = [re.match(r"opened (\d+) failed (\d+)", h.stdout.readline()) for h in holders]
        assert all(opened), opened
        n_open = sum(int(o.group(1)) for o in opened)
        open_s = time.monotonic() - t0
        assert n_open >= IDLE - 20, opened   # well past the 1 024 descriptors
        # malformed request lines beside them: one log line each, at most 10 a minute
        for _ in range(100):
            _raw("127.0.0.1", port, b"GET / HTTP/9.9\r\nHost: x\r\n\r\n")
        times = {}
        for k in range(3):
            status, times[f"state {k}"], state = ask("GET", "/api/state")
            assert status == 200 and state["status"]["state"] == "running"
        status, times["stop"], answer = ask("POST", "/api/stop")
        assert status == 200 and answer["state"] in ("stopping", "stopped"), answer
        print(f"{n_open} idle connections opened in {open_s:.1f} s under RLIMIT_NOFILE "
              f"{NOFILE}: " + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in times.items()))
        assert max(times.values()) < 1.0, times
        wait_for(lambda: ask("GET", "/api/state")[2]["status"]["state"] in ("stopped",
                                                                             "finished"),
                 timeout=30, what="the weld stopped")
    finally:
        for h in holders:
            h.stdin.close()
            h.wait(timeout=30)
        console.send_signal(signal.SIGINT)
        try:
            _, err = console.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            console.kill()
            _, err = console.communicate()
    lines = err.strip().splitlines()
    bad = [s for s in lines if "malformed request" in s]
    assert 1 <= len(bad) <= 10, lines[:20]
    assert "Traceback" not in err and len(lines) <= 15, lines[:20]


def test_the_docs_name_the_settings():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "console.md").read_text()
    for f in ("max_connections", "max_connections_per_client", "idle_timeout_s",
              "request_timeout_s", "backlog", "fd_reserve", "bad_requests_logged_per_min",
              "page_allows_eval", "Content-Security-Policy", "frame-ancestors"):
        assert f in doc, f
