"""The console's command line and start request against bad or partial input: a source whose
frames the weld cannot use is refused at startup (one line, exit 2, as ``torchseam replay``
refuses it), a weld that fails is one line in the terminal and a clear message on the page
(never a traceback), a start request that leaves fields out gets the form's defaults (the
config's and the command line's, ``--length-mm`` included), an open-loop weld's summary says
its poses were planned, not sent, and a bind that fails is one line with nothing on stdout.
"""

from __future__ import annotations

import asyncio
import dataclasses
import socket
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from test_console import CELL, NOISE, PARTS, TOKEN, fake_weld, post

from torchseam.console import cli as console_cli
from torchseam.console.config import load_console_config
from torchseam.console.replay import ReplayWeld, replay_console, replay_summary
from torchseam.console.session import RunState
from torchseam.console.sim import make_console
from torchseam.core.errors import FrameError
from torchseam.live.replay import ReplayResult

SIZE = (CELL.camera.width, CELL.camera.height)


@pytest.fixture(scope="module")
def cfg():
    """The shipped settings, unpaced."""
    return dataclasses.replace(load_console_config(), pace=0.0)


@pytest.fixture()
def no_serving(monkeypatch):
    """The console's ``_serve`` replaced by one that records the console and returns at once
    (a console that got as far as serving would otherwise serve until killed)."""
    served: list = []

    async def fake_serve(console, host, port, loopback=True):
        served.append(console)

    monkeypatch.setattr(console_cli, "_serve", fake_serve)
    return served


def _small_folder(path, wh=(60, 50), n=3):
    path.mkdir()
    for i in range(n):
        cv2.imwrite(str(path / f"{i:05d}.png"), np.zeros((wh[1], wh[0], 3), np.uint8))
    return path


def _small_video(path, wh=(328, 246), n=5):
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, wh)
    for _ in range(n):
        w.write(np.zeros((wh[1], wh[0], 3), np.uint8))
    w.release()
    return path


def _one_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in text, text
    return lines[0]


# --------------------------------------------------------------------------- 1: the source

@pytest.mark.parametrize(("make", "wh"), [(_small_folder, (60, 50)),
                                          (_small_video, (328, 246))])
def test_a_wrong_size_source_is_refused_at_startup(tmp_path, capsys, no_serving, make, wh):
    from torchseam.cli import main

    src = make(tmp_path / ("frames" if make is _small_folder else "small.avi"), wh)
    assert main(["console", "--source", str(src), "--port", "0"]) == 2
    out, err = capsys.readouterr()
    line = _one_line(err)
    assert out == "" and not no_serving
    assert line.startswith("torchseam console: error: ") and str(src) in line
    assert f"frame is {wh[0]} x {wh[1]} px, the camera is configured for " \
           f"{SIZE[0]} x {SIZE[1]}" in line


@pytest.mark.parametrize(("kind", "says"), [
    ("broken", "cannot be opened as a video"),
    ("empty", "no frame could be decoded"),   # opens, and has no frame: found by reading one
])
def test_a_video_without_a_decodable_frame_is_refused_at_startup(tmp_path, capsys, no_serving,
                                                                 kind, says):
    from torchseam.cli import main

    bad = tmp_path / f"{kind}.avi"
    if kind == "broken":
        bad.write_bytes(b"RIFF" + b"\0" * 400)
    else:
        _small_video(bad, SIZE, n=0)
    assert main(["console", "--source", str(bad), "--port", "0"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line == f"torchseam console: error: {bad}: {says}" + (
        " (not a video file, or OpenCV has no decoder for it)" if kind == "broken" else "")
    assert not no_serving


def test_a_weld_that_fails_is_one_line_and_a_clear_message(cfg, capsys):
    def weld(params, observer, control):
        raise FrameError("rec/00007.png: frame is 60 x 50 px, the camera is configured for "
                         "656 x 492")

    con = make_console(cfg, CELL, NOISE, weld, 0.04, "fake", open_loop=True)
    con.session.start(con.validate({}))
    assert con.session.join(10) and con.session.state == RunState.FAILED
    why = "rec/00007.png: frame is 60 x 50 px, the camera is configured for 656 x 492"
    line = _one_line(capsys.readouterr().err)
    assert line == f"torchseam console: weld 1 failed: {why}"
    assert [m[3] for m in con.session.messages if m[2] == "error"] == [f"weld 1 failed: {why}"]
    st = con.session.status()
    assert st["state"] == RunState.FAILED and st["error"] == why


def test_a_weld_that_breaks_is_one_line_naming_where(cfg, capsys):
    def weld(params, observer, control):
        return {}["no such key"]

    con = make_console(cfg, CELL, NOISE, weld, 0.04, "fake")
    con.session.start(con.validate({}))
    assert con.session.join(10) and con.session.state == RunState.FAILED
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("torchseam console: weld 1 failed: internal error (KeyError: ")
    assert "test_console_input.py:" in line
    assert con.session.status()["error"].startswith("internal error (KeyError")


def test_a_source_that_fails_after_its_first_frame_fails_the_weld_in_one_line(
        cfg, tmp_path, capsys):
    """Frame 0 passes the startup check; the weld fails on the frames themselves (no stripe
    on a black frame 0 here, a wrong size on frame 1 otherwise): one line, state failed."""
    src = _small_folder(tmp_path / "frames", SIZE, n=1)
    cv2.imwrite(str(src / "00001.png"), np.zeros((50, 60, 3), np.uint8))
    con = replay_console(src, cfg, CELL, NOISE, PARTS)
    con.session.start(con.validate({}))
    assert con.session.join(30) and con.session.state == RunState.FAILED
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("torchseam console: weld 1 failed: frame 0") and "internal" not in line
    assert con.session.status()["error"]


# --------------------------------------------------------------------------- 3: the defaults

def test_a_start_with_partial_fields_uses_the_defaults(cfg):
    con = make_console(cfg, CELL, NOISE, fake_weld(), 0.04, "fake",
                       defaults={"segments": "bc", "length_mm": 20, "noise": "0.3"})
    con.token = TOKEN
    host, port = con.start_in_thread("127.0.0.1", 0)
    url = f"http://{host}:{port}"
    try:
        status, body = post(url + "/api/start", {"segments": "a"})
        assert status == 200, body
        p = body["params"]
        proc = CELL.process
        assert (p["step_mm"], p["look_ahead_mm"], p["weld_speed_mm_s"]) == \
            (proc.step_mm, proc.look_ahead_mm, proc.weld_speed_mm_s)
        assert p["segments"] == "a" and p["length_mm"] == 20.0 and p["noise"] == 0.3
        assert p["seed"] == 0 and p["tracker"] == "anchored" and p["faults"] == []
        assert post(url + "/api/stop")[0] == 200 and con.session.join(10)
        # sent empty (the page's cleared field), the length is the request's: whole segments
        status, body = post(url + "/api/start", {"length_mm": "", "step_mm": 1.5})
        assert status == 200 and body["params"]["length_mm"] is None
        assert body["params"]["step_mm"] == 1.5 and body["params"]["segments"] == "bc"
        assert post(url + "/api/stop")[0] == 200 and con.session.join(10)
        # a field sent null or bad is still refused by name
        status, body = post(url + "/api/start", {"step_mm": None})
        assert status == 400 and body["error"] == "step_mm: missing"
        status, body = post(url + "/api/start", {"colour": "red"})
        assert status == 400 and body["error"].startswith("colour: unknown parameter")
    finally:
        if con.session.running:
            con.session.stop()
            con.session.join(10)
        con.stop_thread()


def test_length_and_segments_from_the_command_line(no_serving):
    from torchseam.cli import main

    assert main(["console", "--length-mm", "25", "--segments", "b", "--port", "0"]) == 0
    (con,) = no_serving
    p = con.validate({})
    assert p.length_mm == 25.0 and p.segments == "b"
    assert con.validate({"segments": "ac"}).length_mm == 25.0
    assert con.defaults["length_mm"] == 25.0
    assert main(["console", "--port", "0"]) == 0
    assert no_serving[1].validate({}).length_mm is None   # no --length-mm: whole segments


# --------------------------------------------------------------------------- 2: open loop

def test_an_open_loop_summary_says_planned_not_sent(cfg):
    empty = np.zeros((0,))
    res = ReplayResult(empty.astype(int), empty, np.zeros((0, 2)), empty.astype(int),
                       np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 3)),
                       [SimpleNamespace(ok=True)] * 5 + [SimpleNamespace(ok=False)],
                       {}, (1.0, 2.0), False)
    s = replay_summary(res)
    assert s["poses_planned"] == 5 and s["poses_refused"] == 1 and s["poses_sent"] == 0

    con = make_console(cfg, CELL, NOISE, lambda p, obs, ctl: ReplayWeld(res, s), 0.04, "fake",
                       open_loop=True)
    con.session.start(con.validate({}))
    assert con.session.join(10) and con.session.state == RunState.FINISHED
    done = [m[3] for m in con.session.messages if "finished:" in m[3]]
    assert len(done) == 1 and "poses planned (open loop, not sent) 5, refused 1" in done[0]
    assert "poses sent" not in done[0]
    assert con.session.status()["open_loop"] is True


# --------------------------------------------------------------------------- 4: the bind

def test_a_failed_bind_is_one_line_and_nothing_on_stdout(capsys):
    from torchseam.cli import main

    with socket.socket() as s:
        s.bind(("0.0.0.0", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["console", "--host", "0.0.0.0", "--port", str(port)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert _one_line(err) == (f"torchseam console: error: cannot serve on 0.0.0.0:{port}: "
                              "Address already in use")


def test_the_not_loopback_warning_goes_to_stderr_after_the_bind(capsys):
    async def start(host, port):
        return host, port

    async def close():
        pass

    con = SimpleNamespace(start=start, close=close, url=lambda: "http://0.0.0.0:1/?token=t",
                          session=SimpleNamespace(running=False))

    async def serve_briefly():
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(console_cli._serve(con, "0.0.0.0", 1, loopback=False), 0.2)

    asyncio.run(serve_briefly())
    out, err = capsys.readouterr()
    assert out.strip() == "torchseam console on http://0.0.0.0:1/?token=t  (Ctrl-C stops)"
    line = _one_line(err)
    assert line.startswith("torchseam console: warning: bound to 0.0.0.0, not loopback")
