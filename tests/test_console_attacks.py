"""The operator console against requests that are not its operator's (issue 25): a DNS-rebinding
page (its own name resolving to 127.0.0.1, so ``Origin`` and ``Host`` agree), other sites' pages,
requests without the per-run token, and bodies built to break the parser (huge numbers, deep
nesting, booleans as numbers, duplicates). Each gets its 4xx with a message, never a 500; a weld
started with the token beside them runs to its end with no unsafe pose.

The console runs as in ``tests/test_console.py`` (its fake weld and ``served`` fixture); the
requests go through ``http.client`` so that ``Host`` and ``Origin`` are exactly what a browser
on a rebinding page would send.
"""

from __future__ import annotations

import asyncio
import dataclasses
import http.client
import json
import socket
import time

import aiohttp
import pytest
from test_console import CELL, GOOD, NOISE, PART, PARTS, TOKEN, _noise, fake_console, post, wait_for

from torchseam.console.config import load_console_config, parse_params
from torchseam.console.server import MAX_BODY, TOKEN_HEADER, split_host
from torchseam.console.session import RunState
from torchseam.console.sim import simulated_console
from torchseam.live.demo import FAULTS
from torchseam.track.peers import TRACKERS

pytestmark = pytest.mark.realtime  # wall-clock timing: run alone (README's test command)

SHIPPED = (CELL, PART, NOISE, PARTS)  # the cell, part, noise and live parts of the console
EVIL = "evil.example"
REAL = "the address connected to"


@pytest.fixture(scope="module")
def cfg():
    """The shipped settings, unpaced (as in tests/test_console.py)."""
    return dataclasses.replace(load_console_config(), pace=0.0)


@pytest.fixture()
def served(cfg):
    """A console with test_console's fake weld and token on an ephemeral loopback port."""
    made = []

    def make(c=cfg, **kw):
        con = fake_console(c, **kw)
        host, port = con.start_in_thread("127.0.0.1", 0)
        made.append(con)
        return con, f"http://{host}:{port}"

    yield make
    for con in made:
        if con.session.running:
            con.session.stop()
            con.session.join(10)
        con.stop_thread()


def request(url: str, method: str, path: str, body: bytes | dict | None = None,
            host: str | None = REAL, token: str | None = None,
            headers: dict | None = None) -> tuple[int, dict]:
    """One request with exactly these headers: ``host`` :data:`REAL` the address connected
    to, None no Host header at all."""
    h, p = url.removeprefix("http://").rsplit(":", 1)
    conn = http.client.HTTPConnection(h, int(p), timeout=10)
    data = json.dumps(body).encode() if isinstance(body, dict) else body
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        if host is not None:
            conn.putheader("Host", f"{h}:{p}" if host is REAL else host)
        if token is not None:
            conn.putheader(TOKEN_HEADER, token)
        for k, v in (headers or {}).items():
            conn.putheader(k, v)
        if data is not None:
            conn.putheader("Content-Type", "application/json")
        conn.putheader("Content-Length", str(len(data or b"")))
        conn.endheaders(data)
        r = conn.getresponse()
        raw = r.read()
    finally:
        conn.close()
    try:
        return r.status, json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return r.status, {"text": raw[:200]}


def port_of(url: str) -> int:
    return int(url.rsplit(":", 1)[1])


async def ws_status(url: str, path: str = "/ws", headers: dict | None = None) -> int:
    """101 when the WebSocket opens (and gets its hello), else the handshake's HTTP status."""
    try:
        async with aiohttp.ClientSession() as s, \
                s.ws_connect(url.replace("http", "ws") + path, headers=headers or {}) as ws:
            msg = await ws.receive(timeout=10)
            assert json.loads(msg.data)["type"] == "hello"
            return 101
    except aiohttp.WSServerHandshakeError as e:
        return e.status


# --------------------------------------------------------------------------- Host and Origin

def test_dns_rebinding_requests_are_refused(served):
    """The issue's requests: a page on evil.example (resolving to 127.0.0.1) posts with its own
    Host and Origin. 403 for each, even with the right token; nothing starts or stops."""
    con, url = served()
    port = port_of(url)
    evil = {"host": f"{EVIL}:{port}", "headers": {"Origin": f"http://{EVIL}:{port}"}}
    for token in (None, TOKEN):
        status, body = request(url, "POST", "/api/start", GOOD, token=token, **evil)
        assert status == 403 and "not this console" in body["error"], body
        assert not con.session.running and con.session.weld_id == 0
    assert post(url + "/api/start", GOOD)[0] == 200       # the operator's weld
    wait_for(lambda: con.session.latest is not None, what="the first frame")
    for action in ("stop", "hold"):
        assert request(url, "POST", f"/api/{action}", {}, token=TOKEN, **evil)[0] == 403
    # reads are refused too: the rebinding page would read them as its own origin
    for path in ("/", "/api/state", "/frame.jpg", "/api/auth"):
        assert request(url, "GET", path, **evil)[0] == 403, path
    ws = asyncio.run(ws_status(url, f"/ws?token={TOKEN}",
                               {"Host": f"{EVIL}:{port}", "Origin": f"http://{EVIL}:{port}"}))
    assert ws == 403
    assert con.session.running and con.session.state == RunState.RUNNING
    assert not con.session.control.held and not con.session.control.stopped


def test_host_allow_list(served):
    con, url = served()
    port = port_of(url)
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"LocalHost:{port}", f"[::1]:{port}",
                 f"[0:0:0:0:0:0:0:1]:{port}"):
        assert request(url, "GET", "/api/state", host=host)[0] == 200, host
    for host in (f"{EVIL}:{port}", f"127.0.0.1:{port + 1}", "127.0.0.1", f"localhost.:{port}",
                 f"127.0.0.1.nip.io:{port}", f"127.0.0.2:{port}", f"0.0.0.0:{port}",
                 f"[::1]x:{port}", f"127.0.0.1:{port}:{port}", f"127.0.0.1:+{port}",
                 f"user@127.0.0.1:{port}", ""):
        status, body = request(url, "GET", "/api/state", host=host)
        assert status == 403 and "not this console" in body["error"], host
    # no Host at all: aiohttp's parser refuses HTTP/1.1 without one (400); HTTP/1.0 may omit
    # it, and the console refuses that
    assert request(url, "GET", "/", host=None)[0] == 400
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    sock.sendall(b"GET /api/state HTTP/1.0\r\n\r\n")
    assert sock.recv(100).startswith(b"HTTP/1.0 403")
    sock.close()
    # a name the operator allowed (--allow-host): answered, with this port only
    con.allowed_hosts = ("cell-pc.local",)
    assert request(url, "GET", "/api/state", host=f"cell-pc.local:{port}")[0] == 200
    assert request(url, "GET", "/api/state", host=f"cell-pc.local:{port + 1}")[0] == 403


def test_split_host():
    assert split_host("LOCALHOST:8642") == ("localhost", 8642)
    assert split_host("[::1]:8642") == ("[::1]", 8642)
    assert split_host("127.0.0.1") == ("127.0.0.1", 80)
    assert split_host("127.0.0.1", 443) == ("127.0.0.1", 443)
    for bad in ("", ":8642", "[::1", "a:b", "a:1:2", "a:١٢", "a:1234567"):
        assert split_host(bad) is None, bad


def test_a_foreign_origin_is_refused(served):
    con, url = served()
    port = port_of(url)
    for origin in ("http://evil.example", f"http://{EVIL}:{port}", "null",
                   f"http://127.0.0.1:{port + 1}", f"file://127.0.0.1:{port}",
                   f"http://127.0.0.1:{port}@evil.example", f"http://127.0.0.1:{port}/x",
                   f"http://[::1:{port}", "x" * 1000):
        status, body = request(url, "POST", "/api/start", GOOD, token=TOKEN,
                               headers={"Origin": origin})
        assert status == 403 and "are not accepted" in body["error"], origin
        assert request(url, "GET", "/api/state", headers={"Origin": origin})[0] == 403
        ws = asyncio.run(ws_status(url, f"/ws?token={TOKEN}", {"Origin": origin}))
        assert ws == 403, origin
    assert not con.session.running and con.session.weld_id == 0
    # the page's own origin, by any of the console's names
    for origin in (f"http://127.0.0.1:{port}", f"http://localhost:{port}"):
        assert request(url, "GET", "/api/state", headers={"Origin": origin})[0] == 200


# --------------------------------------------------------------------------- the token

def test_state_changes_and_the_stream_need_the_token(served):
    con, url = served()
    port = port_of(url)
    for path in ("/api/start", "/api/hold", "/api/resume", "/api/stop"):
        for token, why in ((None, "needs the console's token"), ("", "needs the console's"),
                           ("wrong", "wrong token"), (TOKEN + "x", "wrong token"),
                           (TOKEN[:-1], "wrong token"), ("tést", "wrong token")):
            status, body = post(url + path, GOOD, token=token)
            assert status == 403 and why in body["error"], (path, token, body)
        # the query parameter is for the WebSocket only: a link cannot post with it
        assert request(url, "POST", f"{path}?token={TOKEN}", GOOD)[0] == 403
    assert request(url, "POST", "/api/start", GOOD,
                   headers={TOKEN_HEADER: "tést".encode().decode("latin-1")})[0] == 403
    assert not con.session.running and con.session.weld_id == 0
    # the WebSocket: the token as ?token= (a browser) or the header (other clients)
    assert asyncio.run(ws_status(url)) == 403
    assert asyncio.run(ws_status(url, "/ws?token=wrong")) == 403
    assert asyncio.run(ws_status(url, "/ws?token=")) == 403
    assert asyncio.run(ws_status(url, f"/ws?token={TOKEN}")) == 101
    assert asyncio.run(ws_status(url, headers={TOKEN_HEADER: TOKEN})) == 101
    # other methods and unknown paths are not token-free either
    for method, path in (("PUT", "/api/start"), ("DELETE", "/api/stop"), ("GET", "/nope")):
        assert request(url, method, path, {})[0] == 403, (method, path)
    # the page and read-only state need no token (the page reads it from its address)
    assert request(url, "GET", "/")[0] == 200
    assert request(url, "GET", "/api/state")[0] == 200
    assert request(url, "GET", "/api/auth")[0] == 403
    assert request(url, "GET", "/api/auth", token=TOKEN) == (200, {"ok": True})
    assert request(url, "GET", "/", host=f"localhost:{port}")[0] == 200


def test_each_console_makes_its_own_token(cfg):
    a, b = simulated_console(cfg, *SHIPPED), simulated_console(cfg, *SHIPPED)
    assert a.token != b.token and len(a.token) >= 40
    assert fake_console(cfg).token == TOKEN   # tests pass a known one


# --------------------------------------------------------------------------- bodies

@pytest.mark.parametrize(("body", "status", "message"), [
    ('{"seed": %s}' % ("7" * 400), 400, "seed: a number of 400 characters is too long"),
    ('{"seed": %s}' % ("7" * 5000), 400, "seed: a number of 5000 characters is too long"),
    ('{"step_mm": %s}' % ("2" * 400), 400, "step_mm: a number of 400 characters is too long"),
    ('{"step_mm": 2.%s}' % ("0" * 400), 400, "step_mm: a number of 402 characters"),
    ('{"faults": [%s]}' % ("1" * 400), 400, "faults[0]: a number of 400 characters"),
    ("[" * 30000 + "]" * 30000, 413, "parameters: the request is larger than 16 KiB"),
    ("[" * 5000 + "]" * 5000, 400, "parameters: JSON nested deeper than 4 levels"),
    ('{"faults": [[[[["a"]]]]]}', 400, "parameters: JSON nested deeper than 4 levels"),
    ('{"segments": "[[[[[[[[", "a": "\\"[[[[["}', 400, "a: unknown parameter"),
    ('{"seed": 1, "seed": 2}', 400, "seed: given twice"),
    ("{'seed': 1}", 400, "parameters: the request is not JSON"),
    ("[1, 2]", 400, "parameters: expected a JSON object"),
    (b"\xff\xfe{}", 400, "parameters: the request is not UTF-8 JSON"),
    ("7" * 5000, 400, "parameters: expected a JSON object"),
    ("x" * (MAX_BODY + 1), 413, "larger than 16 KiB"),
])
def test_bodies_built_to_break_the_parser_get_a_4xx(served, body, status, message):
    con, url = served()
    raw = body if isinstance(body, bytes) else body.encode()
    got, answer = post(url + "/api/start", raw)
    assert got == status and message in answer["error"], answer
    assert not con.session.running and con.session.weld_id == 0


@pytest.mark.parametrize(("change", "message"), [
    ({"seed": "7" * 400}, "seed: 400 characters is too long for a number"),
    ({"step_mm": "2" * 5000}, "step_mm: 5000 characters is too long for a number"),
    ({"seed": 10 ** 30}, "seed: a 31-digit number is too large"),
    ({"noise": True}, "noise: expected a level name or a number, got True"),
    ({"noise": False}, "noise: expected a level name or a number"),
    ({"noise": 10 ** 30}, "noise: a 31-digit number is too large"),
    ({"noise": ["heavy"]}, "noise: expected a level name or a number"),
    ({"step_mm": True}, "step_mm: True is not a number"),
    ({"seed": False}, "seed: False is not a number"),
    ({"length_mm": True}, "length_mm: True is not a number"),
    ({"weld_speed_mm_s": [8]}, "weld_speed_mm_s: [8] is not a number"),
    ({"faults": ["laser-off", "laser-off"]}, "faults: 'laser-off' is given twice"),
    ({"faults": "arc-flash,arc-flash"}, "faults: 'arc-flash' is given twice"),
    ({"faults": [True]}, "faults: expected fault names, got True"),
    ({"faults": {"laser-off": 1}}, "faults: expected a list of names"),
    ({"faults": ["x"] * 100}, "faults: 100 entries"),
    ({"segments": ["a"]}, "segments: expected text, got ['a']"),
    ({"segments": 1}, "segments: expected text, got 1"),
    ({"tracker": None}, "tracker: expected text, got None"),
    ({"tracker": "t" * 5000}, "tracker: 5000 characters is too long"),
])
def test_strict_parameters_over_http(served, change, message):
    con, url = served()
    status, body = post(url + "/api/start", {**GOOD, **change})
    assert status == 400 and body["error"].startswith(message), body
    assert len(body["error"]) < 300       # a huge value is not echoed back
    assert not con.session.running


def test_strict_parameters_parse(cfg):
    with pytest.raises(ValueError, match="noise: expected"):
        parse_params({**GOOD, "noise": True}, cfg.limits, _noise(), FAULTS, TRACKERS)
    p = parse_params({**GOOD, "noise": 1, "faults": ["laser-off", " arc-flash "]}, cfg.limits,
                     _noise(), FAULTS, TRACKERS)
    assert p.noise == 1.0 and p.faults == ("laser-off", "arc-flash")


def test_hold_when_held_and_resume_when_running_conflict(served):
    con, url = served()
    assert post(url + "/api/start", GOOD)[0] == 200
    wait_for(lambda: con.session.latest is not None, what="the first frame")
    status, body = post(url + "/api/resume")
    assert status == 409 and body["error"] == "resume: the weld is not held"
    assert post(url + "/api/hold")[0] == 200
    status, body = post(url + "/api/hold")
    assert status == 409 and body["error"] == "hold: the weld is already held"
    assert con.session.control.held
    assert post(url + "/api/resume")[0] == 200
    assert post(url + "/api/stop")[0] == 200
    assert con.session.join(10) and con.session.state == RunState.STOPPED
    assert post(url + "/api/stop")[0] == 409
    assert post(url + "/api/hold")[0] == 409


# --------------------------------------------------------------------------- a weld beside them

def _attacks(url: str) -> list[tuple[str, int, tuple[int, ...]]]:
    """Every attack once: (what, status, statuses expected)."""
    port = port_of(url)
    evil = {"host": f"{EVIL}:{port}", "headers": {"Origin": f"http://{EVIL}:{port}"}}
    out = []
    for action in ("start", "hold", "stop"):
        out.append((f"rebinding {action}",
                    request(url, "POST", f"/api/{action}", GOOD, **evil)[0], (403,)))
        out.append((f"no token {action}", post(url + f"/api/{action}", GOOD, token=None)[0],
                    (403,)))
        out.append((f"wrong token {action}", post(url + f"/api/{action}", GOOD, "wrong")[0],
                    (403,)))
        out.append((f"foreign origin {action}", post(url + f"/api/{action}", GOOD,
                                                     origin="http://evil.example")[0], (403,)))
    for name, body in (("5000 digits", b'{"seed": %s}' % (b"9" * 5000)),
                       ("nested", b"[" * 30000 + b"]" * 30000),
                       ("bool noise", json.dumps({**GOOD, "noise": True}).encode()),
                       ("duplicate fault",
                        json.dumps({**GOOD, "faults": ["laser-off"] * 2}).encode())):
        # with the token: refused for the body (a weld runs: 400 / 413 before the 409)
        out.append((name, post(url + "/api/start", body)[0], (400, 413)))
    out.append(("ws without token", asyncio.run(ws_status(url)), (403,)))
    out.append(("rebinding ws", asyncio.run(ws_status(
        url, f"/ws?token={TOKEN}", {"Host": f"{EVIL}:{port}"})), (403,)))
    return out


def test_a_weld_beside_the_attacks_finishes_safely(cfg):
    """A short simulated weld (segment a, 20 mm) started with the token runs to its end while
    every attack above is sent over and over: each gets its 4xx, none holds, stops or
    restarts the weld, and no unsafe pose is sent."""
    # paced (twice real time: about 4 s, long enough for many rounds of attacks), at normal
    # priority: the attacks need the CPU too
    paced = dataclasses.replace(cfg, pace=2.0, rt_priority=0)
    con = simulated_console(paced, *SHIPPED, defaults={"segments": "a", "length_mm": 20})
    con.token = TOKEN
    host, port = con.start_in_thread("127.0.0.1", 0)
    url = f"http://{host}:{port}"
    seen: list[tuple[str, int, tuple[int, ...]]] = []
    try:
        params = {**con.defaults, "noise": "heavy", "seed": 3}
        status, body = post(url + "/api/start", params)
        assert status == 200, body
        rounds = 0
        while con.session.running:
            seen += _attacks(url)
            rounds += 1
            time.sleep(0.05)
        assert con.session.join(120)
    finally:
        if con.session.running:
            con.session.stop()
            con.session.join(30)
        con.stop_thread()
    wrong = [(what, got) for what, got, want in seen if got not in want]
    assert not wrong, wrong
    assert rounds >= 4, rounds
    assert con.session.state == RunState.FINISHED, [m[3] for m in con.session.messages][-5:]
    s = con.session.summary
    assert con.session.weld_id == 1 and s["stopped"] is False and s["frames"] > 10
    assert s["unsafe_poses_sent"] == 0 and s["poses_sent"] > 0
    log = [m[3] for m in con.session.messages]
    assert not any("held by the operator" in m or "stop requested" in m for m in log)


def test_the_console_answers_after_the_attacks(served):
    """No attack leaves the server broken: it still starts a weld with the token."""
    con, url = served()
    for _what, got, want in _attacks(url):
        assert got in want
    sock = socket.create_connection(("127.0.0.1", port_of(url)), timeout=5)
    sock.sendall(b"GARBAGE\r\n\r\n")          # not even HTTP
    sock.recv(100)
    sock.close()
    assert post(url + "/api/start", GOOD)[0] == 200
    assert post(url + "/api/stop")[0] == 200 and con.session.join(10)
