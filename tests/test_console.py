"""The operator console (torchseam/console): parameters, server, streams, and the page in
headless Chromium driving a short simulated weld.

The browser test needs Debian's Chromium (``/usr/bin/chromium``): the ``chromium`` fixture
installs it with apt-get when it is missing and fails (never skips) when it cannot.
Set ``TORCHSEAM_SCREENSHOT=1`` to write the screenshot to ``docs/images/console.png``.
"""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import aiohttp
import cv2
import numpy as np
import pytest

from torchseam.console.config import (
    ParamError,
    load_console_config,
    parse_params,
)
from torchseam.console.server import TOKEN_HEADER, ConsoleServer, is_loopback, render_frame
from torchseam.console.session import LatestFrame, RunState, WeldSession
from torchseam.console.sim import simulated_console
from torchseam.core.config import ConfigError, load_cell, load_noise, load_part
from torchseam.live.demo import FAULTS, DemoEvent, DemoResult, FrameRecord
from torchseam.live.loop import Command, LoopState, LoopStats, StepReport
from torchseam.live.parts import load_live_parts
from torchseam.robot.egm import EgmLink
from torchseam.robot.egm.config import load_egm_config
from torchseam.track.peers import TRACKERS

pytestmark = pytest.mark.realtime  # wall-clock timing: run alone (README's test command)

# what the command line reads for the console: the cell, the part, the noise, the live parts
CELL, PART, NOISE, PARTS = load_cell(), load_part(), load_noise(), load_live_parts()

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
#: The tests' console token (a console makes its own, ``secrets.token_urlsafe``, when not given).
TOKEN = "test-token-0123456789"
GOOD = {"step_mm": 2, "look_ahead_mm": 20, "weld_speed_mm_s": 8, "segments": "a",
        "length_mm": "", "noise": "heavy", "seed": 0, "faults": [], "tracker": "anchored"}


@pytest.fixture(scope="module")
def cfg():
    """The shipped settings, unpaced (the weld runs as fast as it can)."""
    return dataclasses.replace(load_console_config(), pace=0.0)


# --------------------------------------------------------------------------- a fast fake weld

def fake_weld(frame_s: float = 0.004, n_frames: int = 100_000):
    """A weld function with the real event types but no simulator: frames as fast as asked."""
    img = np.zeros((492, 656, 3), np.uint8)
    cv2.line(img, (0, 300), (328, 200), (0, 0, 255), 3)
    cv2.line(img, (328, 200), (656, 300), (0, 0, 255), 3)
    link = EgmLink(load_egm_config(), bind=False)

    def weld(params, observer, control) -> DemoResult:
        loop = SimpleNamespace(commands=[], stats=LoopStats(),
                               nominal=np.c_[np.linspace(0, 50, 200), np.zeros((200, 2))])
        k = 0
        for k in range(n_frames):
            if control.checkpoint():
                break
            t = 0.04 * k
            loop.stats.frames += 1
            loop.stats.add_time("frame->command", 1.0, 100)
            cmd = None
            if k % 5 == 0:
                cmd = Command(t, np.array([t, 0, 0.0]), np.array([1, 0, 0, 0.0]), True, "", t)
                loop.commands.append(cmd)
            uv = np.array([328.0 + np.sin(t), 200.0])
            rec = FrameRecord("a", t, True, uv, uv + 0.5, 0, "tracking",
                              np.array([t, 0.1, 0]), np.array([t, 0, 0.0]), 0.1, "")
            T = np.eye(4)
            T[0, 3] = t
            rep = StepReport(LoopState.TRACKING, None, cmd) if k else None
            observer(DemoEvent("a", k, img, rec, rep, T, loop, link))
            time.sleep(frame_s)
        return DemoResult(summary={"frames": k, "stopped": control.stopped,
                                   "seam_rmse_mm": 0.1})

    return weld


def fake_console(cfg, start_bounds=None, **weld_kw) -> ConsoleServer:
    session = WeldSession(cfg, fake_weld(**weld_kw), 0.04)

    def validate(raw):
        return parse_params(raw, cfg.limits, _noise(), FAULTS, TRACKERS, start_bounds)

    extra = {} if start_bounds is None else {
        "start_offset_mm": [-start_bounds[0], start_bounds[0]],
        "start_angle_deg": [-start_bounds[1], start_bounds[1]]}
    return ConsoleServer(cfg, session, validate, GOOD,
                         {"noise": ["clean", "heavy"], "faults": list(FAULTS),
                          "trackers": list(TRACKERS), "segments": "abcdef"}, source="fake",
                         token=TOKEN, extra_limits=extra)


def _noise():
    from torchseam.core.config import load_noise

    return load_noise()


@pytest.fixture()
def served(cfg):
    """A console with the fake weld on an ephemeral loopback port; stopped afterwards."""
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


def post(url: str, body: dict | bytes | None = None, origin: str | None = None,
         token: str | None = TOKEN, headers: dict | None = None) -> tuple[int, dict]:
    """POST ``body`` (JSON, or bytes as they are) with the token header (None: without)."""
    data = body if isinstance(body, bytes) else json.dumps(body or {}).encode()
    req = urllib.request.Request(url, data=data, method="POST",
                                 headers={"Content-Type": "application/json",
                                          **({"Origin": origin} if origin else {}),
                                          **({TOKEN_HEADER: token} if token else {}),
                                          **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        body = e.read()
        try:
            return e.code, json.loads(body)
        except json.JSONDecodeError:
            return e.code, {"error": body.decode()}


def wait_for(cond, timeout: float = 20.0, what: str = "condition"):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = cond()
        if v:
            return v
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


async def read_ws(url: str, n_updates: int, token: str = TOKEN) -> list[dict | bytes]:
    out: list[dict | bytes] = []
    async with aiohttp.ClientSession() as s, \
            s.ws_connect(url.replace("http", "ws") + f"/ws?token={token}") as ws:
        async for msg in ws:
            out.append(msg.data if msg.type == aiohttp.WSMsgType.BINARY
                       else json.loads(msg.data))
            if sum(isinstance(m, dict) for m in out) >= n_updates:
                break
    return out


# --------------------------------------------------------------------------- config and params

def test_config_loads_and_bad_fields_name_the_field(cfg, tmp_path):
    assert cfg.server.port > 0 and cfg.publish.jpeg_rate_hz > 0
    assert cfg.limits.step_mm[0] < cfg.limits.step_mm[1]
    text = (ROOT / "configs" / "console.yaml").read_text()
    bad = tmp_path / "console.yaml"
    bad.write_text(text.replace("jpeg_quality: 70", "jpeg_quality: 0"))
    with pytest.raises(ConfigError, match="publish.jpeg_quality"):
        load_console_config(bad)


@pytest.mark.parametrize(("change", "message"), [
    ({"step_mm": 9}, "step_mm must be in 0.5..5 mm, got 9"),
    ({"step_mm": "two"}, "step_mm: 'two' is not a number"),
    ({"weld_speed_mm_s": 0}, "weld_speed_mm_s must be in 1..20 mm/s, got 0"),
    ({"look_ahead_mm": None}, "look_ahead_mm: missing"),
    ({"length_mm": -3}, "length_mm must be in 1..400 mm, got -3"),
    ({"segments": "axz"}, "segments must be distinct letters from abcdef"),
    ({"noise": "loud"}, "noise: noise level 'loud'"),
    ({"seed": 1.5}, "seed must be a whole number in 0..2147483647, got 1.5"),
    ({"seed": -1}, "seed must be in 0..2147483647, got -1"),
    ({"faults": ["meteor"]}, "faults: 'meteor' is not one of"),
    ({"tracker": "magic"}, "tracker must be one of"),
    ({"colour": "red"}, "colour: unknown parameter"),
])
def test_bad_parameters_are_refused_with_a_message(cfg, change, message):
    with pytest.raises(ParamError, match=message.replace("(", r"\(").replace(".", r"\.")):
        parse_params({**GOOD, **change}, cfg.limits, _noise(), FAULTS, TRACKERS)


def test_good_parameters_parse(cfg):
    p = parse_params({**GOOD, "segments": "ca", "length_mm": "12", "noise": "0.3",
                      "faults": "laser-off, arc-flash", "step_mm": "1.5"},
                     cfg.limits, _noise(), FAULTS, TRACKERS)
    assert p.segments == "ac" and p.length_mm == 12.0 and p.noise == 0.3
    assert p.faults == ("laser-off", "arc-flash") and p.step_mm == 1.5
    assert parse_params(GOOD, cfg.limits, _noise(), FAULTS, TRACKERS).length_mm is None


def _search_bounds() -> tuple[float, float]:
    """The start bounds of the simulated console: the seam search's, configs/search.yaml."""
    from torchseam.live.search import load_search_config

    search = load_search_config()
    return search.max_extent_mm, search.max_angle_deg


def test_start_off_the_seam_is_checked_against_the_search_bound(cfg):
    mm, deg = _search_bounds()
    bounds = (mm, deg)

    def parse(**change):
        return parse_params({**GOOD, **change}, cfg.limits, _noise(), FAULTS, TRACKERS, bounds)

    p = parse(start_offset_mm="12.5", start_angle_deg=-deg)
    assert (p.start_offset_mm, p.start_angle_deg) == (12.5, -deg)
    assert p.as_dict()["start_offset_mm"] == 12.5
    p = parse()   # absent: on the seam (an older page, a script)
    assert (p.start_offset_mm, p.start_angle_deg) == (0.0, 0.0)
    assert parse(start_offset_mm="", start_angle_deg=" ").start_offset_mm == 0.0
    for change, message in [
            ({"start_offset_mm": mm + 1}, f"start_offset_mm must be in {-mm:g}..{mm:g} mm, "
                                          f"got {mm + 1:g}"),
            ({"start_angle_deg": -deg - 5}, f"start_angle_deg must be in {-deg:g}..{deg:g} "
                                            f"deg, got {-deg - 5:g}"),
            ({"start_offset_mm": "far"}, "start_offset_mm: 'far' is not a number"),
            ({"start_offset_mm": "nan"}, "start_offset_mm: nan is not a number"),
            ({"start_angle_deg": True}, "start_angle_deg: True is not a number"),
            ({"start_angle_deg": [5]}, "start_angle_deg: [5] is not a number"),
            ({"start_offset_mm": 10**400}, "start_offset_mm: a 401-digit number is too large")]:
        with pytest.raises(ParamError) as e:
            parse(**change)
        assert str(e.value) == message
    # a replay moves no torch: only "on the seam" passes
    ok = parse_params({**GOOD, "start_offset_mm": 0, "start_angle_deg": "0"}, cfg.limits,
                      _noise(), FAULTS, TRACKERS)
    assert (ok.start_offset_mm, ok.start_angle_deg) == (0.0, 0.0)
    with pytest.raises(ParamError, match="start_angle_deg: this console replays frames"):
        parse_params({**GOOD, "start_angle_deg": 5}, cfg.limits, _noise(), FAULTS, TRACKERS)


def test_start_off_the_seam_through_the_api(served):
    mm, deg = _search_bounds()
    con, url = served(start_bounds=(mm, deg))
    status, body = post(url + "/api/start", {**GOOD, "start_offset_mm": mm + 1})
    assert status == 400 and body["error"] == (f"start_offset_mm must be in {-mm:g}..{mm:g} "
                                               f"mm, got {mm + 1:g}")
    status, body = post(url + "/api/start", {**GOOD, "start_angle_deg": {"deg": 5}})
    assert status == 400 and body["error"].startswith("start_angle_deg: ")
    assert con.session.state == RunState.IDLE
    limits = con.hello()[0]["limits"]
    assert limits["start_offset_mm"] == [-mm, mm] and limits["start_angle_deg"] == [-deg, deg]
    assert limits["step_mm"] == list(con.cfg.limits.step_mm)
    status, body = post(url + "/api/start", {**GOOD, "start_offset_mm": "-15",
                                             "start_angle_deg": 10})
    assert status == 200 and body["params"]["start_offset_mm"] == -15.0
    assert body["params"]["start_angle_deg"] == 10.0
    assert post(url + "/api/stop")[0] == 200
    con.session.join(10)


def test_simulated_console_starts_the_demo_off_the_seam(cfg, monkeypatch):
    import torchseam.console.sim as sim
    from torchseam.live.demo import DemoControl

    mm, deg = _search_bounds()
    con = simulated_console(cfg, CELL, PART, NOISE, PARTS)
    assert con.defaults["start_offset_mm"] == 0.0 and con.defaults["start_angle_deg"] == 0.0
    limits = con.hello()[0]["limits"]
    assert limits["start_offset_mm"] == [-mm, mm] and limits["start_angle_deg"] == [-deg, deg]
    with pytest.raises(ParamError, match="start_angle_deg must be in"):
        con.validate({**GOOD, "start_angle_deg": deg + 0.5})
    seen = {}

    def fake_run_demo(*args, **kw):
        seen.update(kw)
        return DemoResult()

    monkeypatch.setattr(sim, "run_demo", fake_run_demo)
    p = con.validate({**GOOD, "start_offset_mm": "20", "start_angle_deg": "-5"})
    sim.sim_weld(CELL, PART, _noise(), PARTS)(p, lambda ev: None, DemoControl())
    assert seen["start_offset_mm"] == 20.0 and seen["start_angle_deg"] == -5.0


def test_loopback_and_cli_registration():
    from torchseam.cli import build_parser

    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5")
    args = build_parser().parse_args(["console"])
    assert args.host == "127.0.0.1" and args.source == "sim" and args.allow_host == []
    args = build_parser().parse_args(["console", "--host", "0.0.0.0", "--allow-host",
                                      "cell-pc.local", "--allow-host", "10.0.0.5"])
    assert args.allow_host == ["cell-pc.local", "10.0.0.5"]


def test_render_frame_is_a_jpeg_of_the_scaled_frame():
    img = np.full((492, 656, 3), 40, np.uint8)
    lf = LatestFrame(7, img, (300.0, 200.0), (301.0, 199.0), 1, "coasting", "a", 1.0, "hi")
    data = render_frame(lf, 0.5, 70)
    out = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert data[:2] == b"\xff\xd8" and out.shape == (246, 328, 3)
    assert img.max() == 40  # the loop's frame is not drawn on


# --------------------------------------------------------------------------- server and streams

def test_page_is_self_contained(served):
    _, url = served()
    html = urllib.request.urlopen(url + "/", timeout=10).read().decode()
    assert "<canvas" in html and "/ws" in html
    for ref in ('src="http', "src='http", 'href="http', "@import", "//cdn"):
        assert ref not in html  # nothing fetched from elsewhere: the cell PC may be offline


def test_start_validation_conflicts_and_actions(served):
    con, url = served()
    status, body = post(url + "/api/hold")
    assert status == 409 and body["error"] == "hold: no weld is running"
    status, body = post(url + "/api/start", {**GOOD, "step_mm": 9})
    assert status == 400 and body["error"] == "step_mm must be in 0.5..5 mm, got 9"
    assert con.session.state == RunState.IDLE
    status, body = post(url + "/api/start", GOOD, origin="http://evil.example")
    assert status == 403 and not con.session.running
    status, body = post(url + "/api/start", GOOD)
    assert status == 200 and body["ok"]
    status, body = post(url + "/api/start", GOOD)
    assert status == 409 and "a weld is running" in body["error"]
    wait_for(lambda: con.session.latest is not None, what="the first frame")

    assert post(url + "/api/hold")[0] == 200
    time.sleep(0.2)
    seq = con.session.latest.seq
    time.sleep(0.4)
    assert con.session.latest.seq == seq, "frames went on while held"
    assert con.session.status()["held"]
    assert post(url + "/api/resume")[0] == 200
    wait_for(lambda: con.session.latest.seq > seq, what="frames after resume")
    assert post(url + "/api/stop")[0] == 200
    assert con.session.join(10)
    assert con.session.state == RunState.STOPPED and con.session.summary["stopped"]
    texts = [m[3] for m in con.session.messages]
    assert any("start refused: step_mm" in t for t in texts)
    assert any("held by the operator" in t for t in texts)


def test_second_client_gets_the_history_and_does_not_disturb_the_weld(served):
    con, url = served()
    assert post(url + "/api/start", GOOD)[0] == 200
    wait_for(lambda: con.session.latest and con.session.latest.seq > 60, what="60 frames")
    first = asyncio.run(read_ws(url, 4))
    hello = first[0]
    assert hello["type"] == "hello" and hello["status"]["state"] == "running"
    n0 = len(hello["frames"]["t"])
    assert n0 >= 60 and len(hello["commands"]["t"]) >= 10 and "a" in hello["nominal"]
    assert any(isinstance(m, bytes) and m[:2] == b"\xff\xd8" for m in first), "no JPEG frame"
    updates = [m for m in first[1:] if isinstance(m, dict)]
    assert all(m["type"] == "update" for m in updates)
    # updates carry only what is new, continuing the snapshot's sequence
    seqs = hello["frames"]["seq"] + [s for m in updates for s in m["frames"]["seq"]]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    weld_id, seq_before = con.session.weld_id, con.session.latest.seq
    second = asyncio.run(read_ws(url, 2))  # a reload / a second tab
    assert second[0]["weld_id"] == weld_id and len(second[0]["frames"]["t"]) > n0
    assert con.session.running and con.session.weld_id == weld_id
    assert con.session.latest.seq > seq_before and con.session.state == RunState.RUNNING
    state = json.loads(urllib.request.urlopen(url + "/api/state", timeout=10).read())
    assert state["type"] == "hello" and len(state["frames"]["t"]) > n0


def test_history_and_observer_stay_small(cfg, served):
    small = dataclasses.replace(cfg, history=dataclasses.replace(
        cfg.history, frames=50, commands=10, messages=5))
    con, url = served(small, frame_s=0.0005)
    assert post(url + "/api/start", GOOD)[0] == 200
    wait_for(lambda: con.session.latest and con.session.latest.seq > 2000, what="2000 frames")
    for k in range(20):
        con.session.log(f"line {k}")
    hello = asyncio.run(read_ws(url, 1))[0]
    assert len(hello["frames"]["t"]) == 50 and len(hello["commands"]["t"]) == 10
    assert len(hello["messages"]) == 5
    per_frame_us = 1e6 * con.session.observer_s / con.session.latest.seq
    assert per_frame_us < 500, f"observer takes {per_frame_us:.0f} us per frame"


def _raw_ws_client(url: str) -> socket.socket:
    """A WebSocket client that completes the handshake and then never reads (a stuck tab)."""
    host, port = url.removeprefix("http://").split(":")
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect((host, int(port)))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /ws?token={TOKEN} HTTP/1.1\r\nHost: {host}:{port}\r\n"
               "Upgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
               "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    return s


@pytest.mark.parametrize("pace", [1.0, 0.0])
def test_a_paced_weld_thread_asks_for_real_time_priority(cfg, pace):
    """Paced, the weld thread runs at ``rt_priority`` (SCHED_FIFO) or says in the log that it
    was refused; flat out it never asks (it would keep a core from everything else)."""
    seen = []

    def weld(params, observer, control):
        seen.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))
        return DemoResult(summary={"frames": 0, "stopped": False})

    session = WeldSession(dataclasses.replace(cfg, pace=pace, rt_priority=7), weld, 0.04)
    session.start(parse_params(GOOD, cfg.limits, _noise(), FAULTS, TRACKERS))
    assert session.join(10)
    log = [m[3] for m in session.messages]
    policy, prio = seen[0]
    if pace == 0:
        assert (policy, prio) == (os.SCHED_OTHER, 0)
        assert not any("real-time" in m for m in log)
    elif policy == os.SCHED_FIFO:
        assert prio == 7
        assert any("weld thread at real-time priority 7" in m for m in log)
    else:
        assert policy == os.SCHED_OTHER
        assert any("real-time priority 7 refused" in m for m in log)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the caller's thread is untouched


def test_the_publisher_works_between_frames_not_during_them(cfg):
    """Each publisher tick (status, JSON, sends: a few ms holding the interpreter lock) starts
    right after a frame has been handed over, in the gap before the next, not at a random
    point of the frame period. The fake loop hands over a frame every 80 ms: ticks at random
    times would come a median 40 ms after the last frame (53 ms measured before the publisher
    waited for frames); the median, not every tick, so a slow machine's late wake-ups pass."""
    handed: list[float] = []
    ticks: list[float] = []

    def weld(params, observer, control):
        link = EgmLink(load_egm_config(), bind=False)
        loop = SimpleNamespace(commands=[], stats=LoopStats(), nominal=np.zeros((2, 3)))
        img = np.zeros((48, 64, 3), np.uint8)
        uv = np.array([30.0, 20.0])
        for k in range(60):
            if control.checkpoint():
                break
            time.sleep(0.030)                      # the frame's work
            rec = FrameRecord("a", 0.04 * k, True, uv, uv, 0, "tracking", np.zeros(3),
                              np.zeros(3), 0.1, "")
            handed.append(time.perf_counter())
            observer(DemoEvent("a", k, img, rec, None, np.eye(4), loop, link))
            time.sleep(0.050)                      # waiting for the camera
        return DemoResult(summary={"frames": 60, "stopped": False})

    fast = dataclasses.replace(cfg, publish=dataclasses.replace(cfg.publish, rate_hz=10.0))
    session = WeldSession(fast, weld, 0.04)
    con = ConsoleServer(fast, session, lambda raw: raw, GOOD, {}, source="fake")
    real_status = session.status
    session.status = lambda: ticks.append(time.perf_counter()) or real_status()
    con.start_in_thread("127.0.0.1", 0)
    try:
        session.start(parse_params(GOOD, cfg.limits, _noise(), FAULTS, TRACKERS))
        assert session.join(60)
    finally:
        con.stop_thread()
    after = np.array([t - max(h for h in handed if h <= t) for t in ticks
                      if handed[0] <= t <= handed[-1]])
    assert len(after) >= 20, f"the publisher ticked {len(after)} times in 4.8 s at 10 Hz"
    assert np.median(after) < 0.012, (
        f"ticks came a median {1e3 * np.median(after):.1f} ms after the last frame")


def test_a_frame_handed_over_after_the_server_closed_does_not_fail_the_weld(cfg):
    """The weld thread may hand over a frame just as the server's loop closes: the wake-up is
    dropped, nothing is raised into the weld, and a closed server unhooks itself."""
    con = fake_console(cfg)
    con.start_in_thread("127.0.0.1", 0)
    hook = con.session.frame_done
    assert hook is not None
    con.stop_thread()
    assert con.session.frame_done is None
    con._want_frame = True  # a publisher was waiting when the loop went away
    hook()


def test_a_client_that_never_reads_is_dropped_and_does_not_slow_the_weld(cfg, served):
    fast = dataclasses.replace(cfg, server=dataclasses.replace(cfg.server, send_timeout_s=1.0),
                               publish=dataclasses.replace(cfg.publish, rate_hz=30.0,
                                                           jpeg_rate_hz=30.0, jpeg_scale=1.0,
                                                           jpeg_quality=95))
    con, url = served(fast, frame_s=0.002)
    assert post(url + "/api/start", GOOD)[0] == 200
    wait_for(lambda: con.session.latest is not None, what="the first frame")
    t0, f0 = time.monotonic(), con.session.latest.seq
    time.sleep(1.0)
    rate_alone = (con.session.latest.seq - f0) / (time.monotonic() - t0)
    stuck = _raw_ws_client(url)
    try:
        wait_for(lambda: len(con.clients) == 1, what="the stuck client to connect")
        t0, f0 = time.monotonic(), con.session.latest.seq
        wait_for(lambda: con.dropped_clients == 1, timeout=60, what="the stuck client's drop")
        rate_stuck = (con.session.latest.seq - f0) / (time.monotonic() - t0)
        assert not con.clients
    finally:
        stuck.close()
    assert rate_stuck > 0.5 * rate_alone, (rate_alone, rate_stuck)
    assert any("too slow" in m[3] for m in con.session.messages)


# --------------------------------------------------------------------------- the browser

@pytest.fixture(scope="session")
def chromium() -> Path:
    """Debian's Chromium; installed with apt-get when missing (root), else the test fails."""
    if not CHROMIUM.exists():
        apt = shutil.which("apt-get")
        if apt is None or os.geteuid() != 0:
            pytest.fail(f"{CHROMIUM} is missing and cannot be installed here (needs root and "
                        "apt-get): run `apt-get install -y chromium` first")
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        for cmd in ([apt, "update", "-q"], [apt, "install", "-y", "-q", "chromium"]):
            r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
            if r.returncode != 0:
                pytest.fail(f"`{' '.join(cmd)}` failed while installing Chromium for the "
                            f"console test:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
        if not CHROMIUM.exists():
            pytest.fail(f"apt-get installed chromium but {CHROMIUM} is still missing")
    return CHROMIUM


def test_page_runs_and_watches_a_simulated_weld(chromium, cfg, tmp_path):
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("the console test needs Playwright: pip install -e '.[dev]'")
    con = simulated_console(cfg, CELL, PART, NOISE, PARTS)
    host, port = con.start_in_thread("127.0.0.1", 0)
    url = f"http://{host}:{port}/"
    assert con.url() == f"{url}?token={con.token}" and len(con.token) >= 40
    shot = (ROOT / "docs" / "images" / "console.png" if os.environ.get("TORCHSEAM_SCREENSHOT")
            else tmp_path / "console.png")
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(chromium), headless=True)
            # (wait_for_function evaluates in the page: the console's policy forbids eval)
            page = browser.new_context(bypass_csp=True,
                                       viewport={"width": 1440, "height": 1000}).new_page()
            page.set_default_timeout(30_000)
            # without the token the page watches nothing and says why
            page.goto(url)
            page.wait_for_function("document.querySelector('#param-error').textContent"
                                   ".includes('no token')")
            page.goto(con.url())   # the address the console prints
            state = page.locator("#run-state")
            page.wait_for_function("document.querySelector('#run-state').dataset.state"
                                   " === 'idle'")
            assert "token" not in page.url, "the token stays in the address bar"
            # idle: a placeholder, not a broken-image icon
            assert page.is_hidden("#frame") and page.is_visible("#frame-idle")
            assert "press Start" in page.inner_text("#frame-idle")
            # the u/v scale holds the bulk of the values: one spike among 40 is clipped
            lo, hi = page.evaluate("robustRange([...Array(40).keys()].map((i) => "
                                   "i === 7 ? 200 : 0.3 * Math.sin(i)), 2)")
            assert -3 < lo < 0 < hi < 3

            def num(sel: str, attr: str | None = None) -> float:
                v = (page.get_attribute(sel, attr) if attr else page.inner_text(sel))
                return float(v) if v not in (None, "", "-") else -1.0

            # a bad value is refused, visibly, and nothing starts
            page.fill("#p-step", "9")
            page.click("#btn-start")
            page.wait_for_function("document.querySelector('#param-error').textContent"
                                   ".includes('step_mm must be in 0.5..5 mm')")
            assert state.get_attribute("data-state") == "idle"
            # the simulated cell can start off the seam, within the search's bound
            mm, _ = _search_bounds()
            assert page.is_visible("#p-off") and page.is_visible("#p-ang")
            assert f"start offset {-mm:g}..{mm:g} mm" in page.inner_text("#limits")
            page.fill("#p-step", "2")
            page.fill("#p-off", str(mm + 1))
            page.click("#btn-start")
            page.wait_for_function("document.querySelector('#param-error').textContent"
                                   f".includes('start_offset_mm must be in {-mm:g}..{mm:g}')")
            assert state.get_attribute("data-state") == "idle"
            page.fill("#p-off", "0")
            # a short simulated weld: segment a, 40 mm (stopped before its end)
            page.fill("#p-seg", "a")
            page.fill("#p-len", "40")
            page.click("#btn-start")
            page.wait_for_function("document.querySelector('#run-state').dataset.state"
                                   " === 'running'")
            page.wait_for_function("+document.querySelector('#frames-shown').textContent > 0",
                                   timeout=30_000)
            src0 = page.get_attribute("#frame", "src")
            assert page.is_visible("#frame") and page.is_hidden("#frame-idle")
            uv0 = num("#plot-uv", "data-points")
            page.wait_for_function(
                f"document.querySelector('#frame').src !== {json.dumps(src0)} && "
                f"+document.querySelector('#plot-uv').dataset.points > {uv0}", timeout=30_000)
            assert num("#plot-err", "data-points") > 0 and num("#seam3d", "data-points") > 0

            page.click("#btn-hold")
            page.wait_for_function("document.querySelector('#run-state').dataset.state"
                                   " === 'held'")
            time.sleep(0.5)  # the frame in flight when hold was pressed
            held_at = num("#frame-seq")
            time.sleep(1.5)
            assert num("#frame-seq") == held_at, "the frame counter moved while held"
            assert con.session.control.held

            # a reload joins the running weld without touching it
            points = num("#plot-uv", "data-points")
            page.reload()
            page.wait_for_function(f"+document.querySelector('#plot-uv').dataset.points"
                                   f" >= {points}")
            assert state.get_attribute("data-state") == "held"
            assert con.session.running and num("#frame-seq") == held_at

            page.click("#btn-resume")
            page.wait_for_function(f"+document.querySelector('#frame-seq').textContent"
                                   f" > {held_at}", timeout=30_000)
            # the screenshot a little into the weld, arc on, poses going out
            page.wait_for_function("+document.querySelector('#frame-seq').textContent > 200"
                                   " && +document.querySelector('#plot-q').dataset.points > 5",
                                   timeout=90_000)
            page.screenshot(path=str(shot), full_page=True)
            page.click("#btn-stop")
            page.wait_for_function("['stopped', 'finished'].includes(document.querySelector("
                                   "'#run-state').dataset.state)", timeout=30_000)
            browser.close()
    except Exception as e:
        raise AssertionError(f"{e}\nconsole status: {con.session.status()}\nlast messages: "
                             f"{[m[3] for m in con.session.messages][-8:]}") from e
    finally:
        if con.session.running:
            con.session.stop()
        con.session.join(30)
        con.stop_thread()
    assert shot.stat().st_size > 10_000
    assert any("held by the operator" in m[3] for m in con.session.messages)
    assert con.session.summary is not None and con.session.summary["stopped"]


# --------------------------------------------------------------------------- recorded frames

REPLAY_FRAMES = 20


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, cell, part, noise):
    """A small clean recording (dataset format with labels.csv and meta.json)."""
    from torchseam.sim.record import write_sequence
    from torchseam.sim.sequence import SequenceSpec

    out = tmp_path_factory.mktemp("console-rec")
    write_sequence(out, cell, part, noise, SequenceSpec(n_frames=REPLAY_FRAMES, level=0.0,
                                                        seed=5, start_mm=40.0), progress=False)
    return out


def test_replay_of_a_recording_runs_through_the_session(cfg, recorded):
    from torchseam.console.replay import replay_console
    from torchseam.console.server import NO_CONTROLLER

    con = replay_console(recorded, cfg, CELL, NOISE, PARTS)
    assert str(recorded) in con.source and "open loop" in con.source
    params = con.validate(GOOD)
    con.session.start(params)
    assert con.session.join(30) and con.session.state == RunState.FINISHED, \
        [m[3] for m in con.session.messages]
    s = con.session.summary
    assert s["frames"] == REPLAY_FRAMES and s["stopped"] is False and s["open_loop"]
    assert s["seam_rmse_mm"] is None and s["poses_refused"] == 0
    # open loop: the poses are planned, none sent (as `torchseam replay` says)
    assert s["poses_planned"] >= 1 and s["poses_sent"] == 0
    assert s["pixel_rmse_px"] < 2.0 and s["latency_p99_ms"] > 0
    hist, _ = con.session.delta(None)
    fr = hist["frames"]
    assert len(fr["t"]) == REPLAY_FRAMES and set(fr["seg"]) == {"replay"}
    # every frame after the start frame tracked, with its label: finite pixel errors
    assert all(u is not None and abs(u) < 5 for u in fr["u_err"][1:])
    assert all(v is not None and abs(v) < 5 for v in fr["v_err"][1:])
    assert con.session.latest.uv is not None
    assert sum(p[0] is not None for p in fr["p"]) >= REPLAY_FRAMES - 3
    assert any(fr["p_true"][-1]) and len(hist["commands"]["t"]) >= 1
    # the robot-link panel: a replay has no controller (no EGM link to read)
    link = con._link_state()
    assert link == {"connected": False, "note": NO_CONTROLLER,
                    "sink_accepted": link["sink_accepted"], "sink_refused": 0}
    assert link["sink_accepted"] >= 1
    # the log speaks of what a replay has: no segments, no torch-vs-seam error
    log = [m[3] for m in con.session.messages]
    assert any("started (open loop): tracker" in m for m in log)
    assert any("finished:" in m and "pixel RMSE" in m and "torch vs seam" not in m
               and "poses planned (open loop, not sent)" in m and "poses sent" not in m
               for m in log)


def test_replay_hold_and_stop(cfg, recorded):
    from torchseam.console.replay import replay_console

    paced = dataclasses.replace(cfg, pace=1.0)   # 25 frames/s: 0.8 s for the recording
    con = replay_console(recorded, paced, CELL, NOISE, PARTS)
    con.session.start(con.validate(GOOD))
    wait_for(lambda: con.session.latest is not None and con.session.latest.seq >= 2,
             what="the first frames")
    con.session.hold()
    # the frame in flight is finished first (a fixed 0.15 s was too short on a machine whose
    # host took its CPUs for longer)
    wait_for(lambda: con.session.control.parked, what="the hold to take effect")
    seq = con.session.latest.seq
    time.sleep(0.3)
    assert con.session.latest.seq == seq, "frames went on while held"
    assert con.session.status()["held"]
    con.session.resume()
    wait_for(lambda: con.session.latest.seq > seq, what="frames after resume")
    con.session.hold()
    con.session.stop()
    assert con.session.join(10) and con.session.state == RunState.STOPPED
    s = con.session.summary
    assert s["stopped"] is True and 2 <= s["frames"] < REPLAY_FRAMES
    assert s["frames"] == len(con.session.delta(None)[0]["frames"]["t"])


def test_console_cli_names_a_missing_source(tmp_path, capsys):
    from torchseam.cli import build_parser, main

    missing = tmp_path / "no-such-recording"
    assert main(["console", "--source", str(missing), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "no such folder or video file" in err
    assert build_parser().parse_args(["console", "--source", str(tmp_path)]).source == \
        str(tmp_path)


def test_a_camera_source_runs_and_its_end_is_reported(cfg, recorded, tmp_path):
    import cv2

    from torchseam.console.replay import replay_console

    # OpenCV opens a stream by name like a device: a video of the recording plays the camera
    video = tmp_path / "camera.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (656, 492))
    for i in range(REPLAY_FRAMES):
        w.write(cv2.imread(str(recorded / f"{i:05d}.png")))
    w.release()
    con = replay_console(f"camera:{video}", cfg, CELL, NOISE, PARTS)
    assert con.source.startswith("live camera") and "open loop" in con.source
    con.session.start(con.validate(GOOD))
    assert con.session.join(60)
    # the stream ending is an error of the camera, named, not a silent finish
    assert con.session.state == RunState.FAILED
    assert any("stream ended" in m[3] for m in con.session.messages)
    frames = con.session.delta(None)[0]["frames"]
    assert len(frames["t"]) >= 2   # the camera's frames went through the loop


@pytest.mark.parametrize(("sig", "code", "welding"), [(signal.SIGTERM, 143, True),
                                                     (signal.SIGINT, 130, True),
                                                     (signal.SIGTERM, 143, False)])
def test_a_signal_stops_the_weld_and_the_console_as_ctrl_c_does(sig, code, welding):
    """SIGTERM (systemd, ``docker stop``, ``kill``) takes Ctrl-C's path: a running weld stops
    at its next frame (its segment not completed, stopped by the signal, arc off), one line on
    stderr says so, the exit code is 128 + the signal's number, and no process of the console
    is left. The console runs in its own session (its process group: anything it started) with
    SIGINT's default action, as a terminal starts it (a pytest-xdist worker ignores SIGINT,
    and a child inherits that)."""
    p = subprocess.Popen(
        [sys.executable, "-m", "torchseam", "console", "--port", "0", "--segments", "a"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        line = p.stdout.readline()
        m = re.search(r"http://127\.0\.0\.1:(\d+)/\?token=(\S+)", line)
        assert m, (line, p.poll())
        port, token = int(m.group(1)), m.group(2)

        def ask(method: str, path: str, body: dict | None = None) -> tuple[int, dict]:
            req = urllib.request.Request(
                f"http://127.0.0.1:{port}{path}", method=method,
                data=None if body is None else json.dumps(body).encode(),
                headers={TOKEN_HEADER: token, "Content-Type": "application/json"})
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, json.loads(r.read())

        def weld_under_way() -> bool:
            st = ask("GET", "/api/state")[1]["status"]
            return st["state"] == "running" and bool(st["frame"]) and st["frame"]["t"] >= 1.0

        if welding:   # 80 mm at 8 mm/s after the approach: still running when signalled
            assert ask("POST", "/api/start", {**GOOD, "length_mm": 80})[0] == 200
            wait_for(weld_under_way, timeout=90, what="the weld under way")
        p.send_signal(sig)
        _, err = p.communicate(timeout=90)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == code, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    said = f"torchseam console: interrupted by {sig.name}: "
    if welding:
        assert lines[0].startswith(said + "weld 1 stopped at t="), lines
        assert f"arc off; not completed: segment a (stopped by {sig.name}" in lines[0], lines
    else:
        assert lines[0] == said + "no weld was running"
    with pytest.raises(ProcessLookupError):   # nothing left in the console's process group
        os.killpg(p.pid, 0)
