"""Does watching the weld slow it? The live loop's latency with the console open vs without.

    .venv/bin/python bench/console.py [--repeats 3] [--segments a] [--length-mm 40]
                                      [--clients 2] [--browser] [--pace P]
                                      [--rt-priority N]

Each repeat welds the same short simulated weld (``run_demo``) twice, in alternating order, at
the console's pacing (``--pace``, default ``configs/console.yaml: pace``, 1.0: the camera's
frame rate, as a cell runs; 0: flat out, the loop then takes a whole core and anything else on
the machine competes with it), and with the console's scheduling of the weld thread
(``--rt-priority``, default ``configs/console.yaml: rt_priority``: SCHED_FIFO while paced, where
granted, in both runs): ``off`` calls :func:`run_demo` directly (no observer, no server); ``on``
runs it through the console (observer, ring buffers, publisher, JPEG encoding) with
``--clients`` headless WebSocket clients (in a child process, as a browser is) reading the whole
stream, plus, with ``--browser``, the page itself open in headless Chromium (Debian's
``/usr/bin/chromium``, through Playwright, driven from a process of its own), and a third run
per repeat, ``off +blank``: no console, Chromium open on an empty page (is it the browser being
there, or what our page does?). Columns: the loop's frame -> command latency p50 / p99
(``DemoResult.summary``), wall time and wall ms per frame (render + loop + simulated controller
+ observer), the JPEG frames and updates the clients got, and the CPU seconds Chromium's
processes used during the weld (``/proc``; Linux). Then the medians over the repeats and,
steadier than one run's p99 (its 4th-slowest of ~380 frames), every frame of the repeats pooled
(p50, p99, p99.9), each with the ratio on / off; the target is within 10 %. One short weld first
warms up (not counted). The machine's load average is printed: on a shared 2-core machine single
runs are noisy.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import multiprocessing as mp
import os
import platform
import time
import urllib.request

import aiohttp
import cv2
import numpy as np
import torch

from torchseam.console.config import load_console_config
from torchseam.console.server import TOKEN_HEADER
from torchseam.console.session import PacedControl
from torchseam.console.sim import simulated_console
from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.report import format_table
from torchseam.live.demo import run_demo
from torchseam.live.parts import load_live_parts
from torchseam.robot.egm import set_realtime_priority

PARTS = load_live_parts()  # the shipped settings and parts of the live stack


def _read_stream(url: str, n: int, stop, counts) -> None:
    """Child process: ``n`` WebSocket clients reading every message until ``stop`` is set;
    ``counts`` gets [JPEG frames, JSON updates, bytes, clients connected]."""

    async def one(s: aiohttp.ClientSession) -> None:
        async with s.ws_connect(url) as ws:
            with counts.get_lock():
                counts[3] += 1
            while not stop.is_set():
                try:
                    msg = await ws.receive(timeout=0.5)
                except asyncio.TimeoutError:
                    continue
                if msg.type not in (aiohttp.WSMsgType.BINARY, aiohttp.WSMsgType.TEXT):
                    break
                with counts.get_lock():
                    counts[0 if msg.type == aiohttp.WSMsgType.BINARY else 1] += 1
                    counts[2] += len(msg.data)

    async def main() -> None:
        async with aiohttp.ClientSession() as s:
            await asyncio.gather(*(one(s) for _ in range(n)))

    asyncio.run(main())


class Reader:
    """Headless clients in a process of their own (as a browser is): read the whole stream."""

    def __init__(self, url: str, n: int, token: str) -> None:
        ctx = mp.get_context("spawn")
        self._stop = ctx.Event()
        self._counts = ctx.Array("q", 4)
        self._proc = ctx.Process(target=_read_stream, daemon=True, args=(
            url.replace("http", "ws") + f"/ws?token={token}", n, self._stop, self._counts))
        self._proc.start()
        t0 = time.monotonic()
        while self._counts[3] < n:
            if time.monotonic() - t0 > 60 or not self._proc.is_alive():
                raise RuntimeError("the headless clients did not connect")
            time.sleep(0.05)

    @property
    def jpeg(self) -> int:
        return int(self._counts[0])

    @property
    def updates(self) -> int:
        return int(self._counts[1])

    def close(self) -> None:
        self._stop.set()
        self._proc.join(timeout=10)


def _browse(conn) -> None:
    """Child process: headless Chromium driven by Playwright; ``conn`` gets ("open", url),
    ("close",) and ("quit",), and answers each. Between commands it keeps Playwright's event
    loop served, as the browser's own process would."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", headless=True)
        page = None
        conn.send("ready")
        while True:
            if page is not None:
                page.wait_for_timeout(100)
            elif not conn.poll(0.1):
                continue
            if not conn.poll():
                continue
            cmd = conn.recv()
            if cmd[0] == "open":
                page = browser.new_page(viewport={"width": 1440, "height": 1000})
                page.goto(cmd[1])
            elif cmd[0] == "close" and page is not None:
                page.close()
                page = None
            elif cmd[0] == "quit":
                browser.close()
                conn.send("bye")
                return
            conn.send("ok")


class Browser:
    """Headless Chromium in a process of its own, Playwright included: a browser on the cell
    PC is not driven from the console's process, so the bench must not be either (Playwright's
    sync client in this process would take the interpreter lock from the weld thread)."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_browse, args=(child,), daemon=True)
        self._proc.start()
        self._call(None, 120)

    def _call(self, cmd, timeout: float = 60) -> None:
        if cmd is not None:
            self._conn.send(cmd)
        if not self._conn.poll(timeout) or self._conn.recv() not in ("ok", "ready", "bye"):
            raise RuntimeError(f"the browser process did not answer {cmd}")

    def open(self, url: str) -> None:
        self._call(("open", url))

    def close_page(self) -> None:
        self._call(("close",))

    def quit(self) -> None:
        self._call(("quit",))
        self._proc.join(timeout=10)


def chromium_cpu_s() -> float:
    """CPU seconds (user + system) of the running Chromium processes, from ``/proc``."""
    total, tick = 0.0, os.sysconf("SC_CLK_TCK")
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/comm") as f:
                if not f.read().startswith("chrom"):
                    continue
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
        except (OSError, IndexError, ValueError):
            continue  # the process ended meanwhile
    return total


def run_off(cell, part, noise, level, args, browser: Browser | None = None) -> dict:
    if browser is not None:  # Chromium there, on an empty page: its cost without our page
        browser.open("about:blank")
        time.sleep(1.0)
    cpu0 = chromium_cpu_s()
    lat: list[float] = []
    # the weld thread's scheduling as the console's (WeldSession._run): real-time when paced
    rt = args.rt_priority > 0 and args.pace > 0 and set_realtime_priority(args.rt_priority,
                                                                           "bench weld")
    t0 = time.perf_counter()
    try:
        res = run_demo(cell, part, noise, level, args.seed, segments=args.segments,
                       length_mm=args.length_mm, control=_paced(cell, args.pace),
                       observer=lambda ev: _keep_latency(ev, lat), parts=PARTS)
    finally:
        if rt:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    wall = time.perf_counter() - t0
    cpu = chromium_cpu_s() - cpu0
    if browser is not None:
        browser.close_page()
    return _row("off" if browser is None else "off +blank", 0, res.summary, wall, 0, 0,
                float("nan"), cpu, lat)


def _keep_latency(ev, out: list[float]) -> None:
    """The frame's frame -> command latency, as :meth:`WeldSession.observe` keeps it."""
    t = ev.loop.stats.timings_ms.get("frame->command")
    if t and ev.report is not None:
        out.append(t[-1])


def _paced(cell, pace: float) -> PacedControl:
    """The console's pacing (:class:`WeldSession` does the same) for the runs without it."""
    return PacedControl(1.0 / cell.process.frame_rate_hz / pace if pace > 0 else 0.0)


def run_on(cell, part, noise, args, browser: Browser | None) -> dict:
    cfg = dataclasses.replace(load_console_config(), pace=args.pace,
                              rt_priority=args.rt_priority)
    con = simulated_console(cfg, cell, part, noise, PARTS)
    host, port = con.start_in_thread("127.0.0.1", 0)
    url = f"http://{host}:{port}"
    reader = Reader(url, args.clients, con.token) if args.clients else None
    if browser is not None:
        browser.open(con.url())   # the address with the token, as the CLI prints it
    time.sleep(1.0)  # let the page load and settle
    cpu0 = chromium_cpu_s()
    params = {**con.defaults, "segments": args.segments, "length_mm": args.length_mm,
              "noise": args.noise, "seed": args.seed}
    req = urllib.request.Request(url + "/api/start", json.dumps(params).encode(),
                                 {"Content-Type": "application/json", TOKEN_HEADER: con.token},
                                 method="POST")
    t0 = time.perf_counter()
    urllib.request.urlopen(req, timeout=10).read()
    con.session.join()  # blocked, not polling: this thread leaves the weld's process alone
    wall = time.perf_counter() - t0
    cpu = chromium_cpu_s() - cpu0
    if reader is not None:
        reader.close()
    if browser is not None:
        browser.close_page()
    con.stop_thread()
    if con.session.summary is None:
        raise RuntimeError("the console's weld failed: " + "; ".join(
            m[3] for m in con.session.messages if m[2] == "error"))
    frames = con.session.summary["frames"]
    obs_us = 1e6 * con.session.observer_s / max(frames, 1)
    mode = "on" + (" +chromium" if browser is not None else "")
    # every frame's latency, from the console's own ring buffer (history.latency frames)
    lat = list(con.session._rings.latency)  # noqa: SLF001 - the bench reads what the page reads
    if len(lat) < frames - 1:
        print(f"  (the console kept the latency of {len(lat)} of {frames} frames: raise "
              "history.latency for pooled figures of longer welds)")
    return _row(mode, args.clients, con.session.summary, wall,
                reader.jpeg if reader else 0, reader.updates if reader else 0, obs_us, cpu, lat)


def _row(mode, clients, s, wall, jpeg, updates, obs_us, browser_cpu, lat) -> dict:
    return {"lat": lat, "mode": mode, "clients": clients, "frames": s["frames"],
            "p50": s["latency_p50_ms"], "p99": s["latency_p99_ms"], "wall": wall,
            "ms_frame": 1e3 * wall / max(s["frames"], 1), "jpeg": jpeg, "updates": updates,
            "observer_us": obs_us, "browser_cpu_s": browser_cpu, "load": os.getloadavg()[0]}


COLS = ("mode", "clients", "frames", "p50", "p99", "wall", "ms_frame", "jpeg", "updates",
        "observer_us", "browser_cpu_s", "load")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--segments", default="a")
    ap.add_argument("--length-mm", type=float, default=40.0)
    ap.add_argument("--noise", default="heavy")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clients", type=int, default=2, help="headless WebSocket clients")
    ap.add_argument("--browser", action="store_true",
                    help="also keep the page open in headless Chromium during 'on' runs")
    ap.add_argument("--pace", type=float, default=None,
                    help="weld no faster than this many times the camera's frame rate, both "
                         "with and without the console (default: configs/console.yaml pace; "
                         "0: flat out)")
    ap.add_argument("--rt-priority", type=int, default=None,
                    help="SCHED_FIFO priority of the paced weld thread, with and without the "
                         "console (default: configs/console.yaml rt_priority; 0: normal)")
    args = ap.parse_args()
    ccfg = load_console_config()
    if args.pace is None:
        args.pace = ccfg.pace
    if args.pace < 0:
        ap.error(f"--pace must be >= 0, got {args.pace:g}")
    if args.rt_priority is None:
        args.rt_priority = ccfg.rt_priority
    if not 0 <= args.rt_priority <= 99:
        ap.error(f"--rt-priority must be in 0..99, got {args.rt_priority}")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    cell, part, noise = load_cell(), load_part(), load_noise()
    level = noise.level(args.noise)
    print(f"console bench: segments {args.segments}, {args.length_mm:g} mm each, noise "
          f"{args.noise}, {args.clients} WebSocket client(s)"
          + (" + Chromium" if args.browser else "")
          + f", {args.repeats} repeat(s), pace {args.pace:g}"
            + (" (camera rate)" if args.pace == 1 else " (flat out)" if args.pace == 0 else "")
            + (f", weld thread SCHED_FIFO {args.rt_priority}"
               if args.rt_priority and args.pace > 0 else ", normal scheduling")
            + f"; {os.cpu_count()} CPUs, Python "
            f"{platform.python_version()}, load {os.getloadavg()[0]:.1f}")
    browser = Browser() if args.browser else None
    run_demo(cell, part, noise, level, args.seed, segments=args.segments, length_mm=1.0,
             parts=PARTS)  # warm-up
    rows = []
    try:
        for k in range(args.repeats):
            order = ["off", "on"] + (["blank"] if browser is not None else [])
            for mode in order if k % 2 == 0 else order[::-1]:
                r = (run_off(cell, part, noise, level, args) if mode == "off"
                     else run_off(cell, part, noise, level, args, browser) if mode == "blank"
                     else run_on(cell, part, noise, args, browser))
                rows.append(r)
                print(format_table(COLS, [[r[c] for c in COLS]]).splitlines()[-1], flush=True)
    finally:
        if browser is not None:
            browser.quit()
    print("\nall runs (latency ms, wall s, ms per frame, observer us per frame, load average)")
    print(format_table(COLS, [[r[c] for c in COLS] for r in rows]))
    groups = {"off": [r for r in rows if r["mode"] == "off"],
              "on": [r for r in rows if r["mode"].startswith("on")],
              "blank": [r for r in rows if r["mode"] == "off +blank"]}
    groups = {m: rs for m, rs in groups.items() if rs}
    med = {m: {c: float(np.median([r[c] for r in rs])) for c in ("p50", "p99", "ms_frame")}
           for m, rs in groups.items()}
    blank = "blank" in med
    print("\nmedians over the repeats, and on / off"
          + (" (blank: no console, Chromium on an empty page)" if blank else ""))
    print(format_table(
        ["figure", "console off", "console on", "on / off"]
        + (["blank Chromium", "blank / off"] if blank else []),
        [[f"frame->command {c}" if c != "ms_frame" else "wall ms per frame",
          med["off"][c], med["on"][c], med["on"][c] / med["off"][c]]
         + ([med["blank"][c], med["blank"][c] / med["off"][c]] if blank else [])
         for c in ("p50", "p99", "ms_frame")]))
    # one run's p99 is its 4th-slowest frame: pooled over the repeats it is steadier
    pooled = {m: np.concatenate([r["lat"] for r in rs]) for m, rs in groups.items()}
    print("\nevery frame of the repeats pooled (frames per mode: "
          + ", ".join(f"{m} {len(v)}" for m, v in pooled.items()) + ")")
    print(format_table(
        ["figure", "console off", "console on", "on / off"]
        + (["blank Chromium", "blank / off"] if blank else []),
        [[f"frame->command {name}", q(pooled["off"]), q(pooled["on"]),
          q(pooled["on"]) / q(pooled["off"])]
         + ([q(pooled["blank"]), q(pooled["blank"]) / q(pooled["off"])] if blank else [])
         for name, q in (("p50", lambda v: float(np.percentile(v, 50))),
                         ("p99", lambda v: float(np.percentile(v, 99))),
                         ("p99.9", lambda v: float(np.percentile(v, 99.9))))]))


if __name__ == "__main__":
    main()
