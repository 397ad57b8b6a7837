"""``torchseam console``: the operator console, a local web page to run and watch the weld."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
from pathlib import Path

from torchseam.console.config import DEFAULT_HOST
from torchseam.core.config import JOINT_PROFILES, MAX_NOISE_LEVEL
from torchseam.core.errors import TorchseamError
from torchseam.core.signals import EXIT_SIGNAL, STOP_SIGNALS, SignalStop

#: Named frame sources; any other ``--source`` is a recorded folder, a video file, or a
#: camera (``camera:N``, a stream URL; see :func:`~torchseam.live.sources.open_source`).
SOURCES = ("sim",)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "console", help="operator console: a local web page to run and watch the weld",
        description="Serve the operator console: one page with the camera frame, the 3D seam "
                    "and torch pose, error and quaternion plots, the EGM link state, the weld "
                    "parameters, start / hold / resume / stop and the message log. It drives "
                    "the same live loop as `torchseam demo` (the simulated cell, closed loop) "
                    "or, with --source DIR|VIDEO|camera:N, as `torchseam replay` (recorded or "
                    "live frames, open loop). Binds to loopback unless --host says otherwise. "
                    "Prints the page's address with a per-run token (/?token=...): starting, "
                    "holding or stopping the weld and the live stream need it.")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help=f"address to bind (default {DEFAULT_HOST}: this machine only)")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                   help="also answer requests whose Host is NAME (with the port), e.g. the "
                        "cell PC's name or address for --host 0.0.0.0; repeatable (always "
                        "answered: localhost, 127.0.0.1, [::1] and --host; default: no other)")
    p.add_argument("--port", type=int, default=None,
                   help="port (default configs/console.yaml server.port; 0: any free port)")
    p.add_argument("--config", type=Path, help="console config (default configs/console.yaml)")
    p.add_argument("--source", default="sim", metavar="sim|DIR|VIDEO|camera:N|URL",
                   help="what feeds the loop: sim (default: the simulated cell, closed loop), "
                        "or a recorded frame folder (dataset format, 00000.png ...), video "
                        "file or live camera (camera:N, a stream URL), run open loop through "
                        "the live loop as `torchseam replay` does: nothing moves, no "
                        "controller; the page's tracker, step, look-ahead and speed apply, "
                        "its noise, seed, faults, segments and "
                        "length do not (a folder named sim: ./sim)")
    p.add_argument("--cell", type=Path, default=None, metavar="FILE",
                   help="weld this cell through its interfaces (a cell file, as `torchseam "
                        "weld --cell`: its camera stream, its controller's EGM and RAPID), "
                        "closed loop; the page's segments, length and tracker apply, its "
                        "noise, seed and faults do not (default: none, the simulated cell or "
                        "--source)")
    p.add_argument("--part", type=Path, help="part config (default configs/parts/t_joint.yaml)")
    p.add_argument("--joint", choices=JOINT_PROFILES, default=None,
                   help="the joint in --source's frames (default: the part's joint a frame "
                        "folder's meta.json names, else fillet; fillet: the page's tracker "
                        "follows TIPM's corner; v_groove, butt, lap: the profile's aim point, "
                        "default tracker only); with the simulated cell or --cell, the part's "
                        "joint: field (a different --joint is refused)")
    p.add_argument("--noise", default="heavy",
                   help="initial arc-noise level on the page: a name from configs/noise.yaml "
                        f"or a number in [0, {MAX_NOISE_LEVEL:g}] (default heavy)")
    p.add_argument("--segments", default="abcdef",
                   help="initial segments on the page, letters of abcdef (default abcdef: "
                        "the whole ring)")
    p.add_argument("--length-mm", type=float, default=None,
                   help="initial length per segment on the page, and of a start request "
                        "that gives none (default: whole segments)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import cv2  # here, not at the top: the parser (--help) needs no OpenCV or torch
    import torch

    from torchseam.console.config import ParamError, load_console_config
    from torchseam.console.replay import replay_console
    from torchseam.console.server import is_loopback
    from torchseam.console.sim import simulated_console
    from torchseam.core.config import load_cell, load_noise, load_part
    from torchseam.live.parts import load_live_parts

    torch.set_num_threads(1)   # as `torchseam demo`: small ops, one thread is fastest
    cv2.setNumThreads(1)
    cfg = load_console_config(args.config)
    port = cfg.server.port if args.port is None else args.port
    if not 0 <= port <= 65535:
        raise TorchseamError(f"--port must be in 0..65535, got {port}")
    defaults = {"noise": args.noise, "segments": args.segments, "length_mm": args.length_mm}
    cell, noise, parts = load_cell(), load_noise(), load_live_parts()
    try:
        if args.source == "sim" or args.cell is not None:
            part = load_part(args.part)
            if args.joint not in (None, part.joint):
                raise TorchseamError(f"--joint {args.joint}: the part "
                                     f"({args.part or 'configs/parts/t_joint.yaml'}) is a "
                                     f"{part.joint} joint (its joint: field); --joint names the "
                                     "joint in --source's recorded frames")
        if args.cell is not None:
            console = _cell_console(args, cfg, noise, parts, defaults)
        elif args.source == "sim":
            console = simulated_console(cfg, cell, part, noise, parts, defaults=defaults)
        else:   # a folder or video: open_source's errors name the path
            joint = args.joint or "fillet"
            if Path(args.source).is_dir():  # its meta.json may name the part's joint (taken
                # silently: stdout's first line is the page's address, stderr one line an
                # error's; a --joint it contradicts is warned of)
                from torchseam.core.dataset import Dataset

                joint, _, warning = Dataset.open(args.source, labels=False).joint(args.joint)
                if warning:
                    print(warning, file=sys.stderr, flush=True)
            parts.tracker("anchored", joint)  # a bad joint, before serving
            console = replay_console(args.source, cfg, cell, noise, parts, defaults=defaults,
                                     joint=joint)
    except ParamError as e:
        raise TorchseamError(str(e)) from None
    console.allowed_hosts = tuple(args.allow_host)
    name = asyncio.run(_serve(console, args.host, port, loopback=is_loopback(args.host)))
    return EXIT_SIGNAL.get(name, 1) if name else 0


def _cell_console(args: argparse.Namespace, cfg, noise, parts, defaults):
    """The console on a cell file: its pre-flight first (a part the robot cannot weld is
    refused here, with the table, as ``torchseam weld`` refuses it)."""
    from torchseam.console.cell import cell_console
    from torchseam.core.config import load_part
    from torchseam.live.cellfile import load_weld_cell
    from torchseam.plan.preflight import preflight

    if args.source != "sim":
        raise TorchseamError("--cell and --source: give one (a cell brings its own camera)")
    cell = load_weld_cell(args.cell)
    part = load_part(args.part)
    name = str(args.part or "configs/parts/t_joint.yaml")
    report = preflight(cell.calibration, part, config=parts.plan, robot=parts.robot,
                       part_name=name)
    if not report.ok:
        print(report.text(), file=sys.stderr)
        raise TorchseamError(f"the robot cannot weld {name}: pre-flight refused segment(s) "
                             f"{', '.join(report.refused)}; nothing moved")
    return cell_console(cfg, cell, part, report, noise, parts, name, defaults=defaults)


#: how long a signal waits for the running weld to stop before the console ends without it
STOP_WAIT_S = 30.0


async def _serve(console, host: str, port: int, loopback: bool = True) -> str | None:
    """Serve until SIGINT or SIGTERM (or the task is cancelled); the signal's name, None
    without one. A signal stops a running weld as the page's Stop does (at its next frame:
    arc off, the robot held; the log and the terminal say which signal), waits for it (at
    most :data:`STOP_WAIT_S`), then closes the pages and the server; a second signal quits at
    once (:class:`~torchseam.core.signals.SignalStop`, as ``torchseam demo``). A signal
    ignored when the console started (a shell's background job's SIGINT) stays ignored."""
    try:
        await console.start(host, port)
    except OSError as e:
        # asyncio's text repeats the address; the system's reason is enough
        why = os.strerror(e.errno) if e.errno else (e.strerror or str(e))
        raise TorchseamError(f"cannot serve on {host}:{port}: {why}") from None
    if not loopback:   # after the bind: a console that cannot serve warns of nothing
        print(f"torchseam console: warning: bound to {host}, not loopback: anyone who can "
              "reach this machine and has the token can start and stop the weld (pages are "
              f"answered as {host} or a --allow-host name)", file=sys.stderr, flush=True)
    loop = asyncio.get_running_loop()
    ended = asyncio.Event()
    # the handler only wakes the loop; the weld is stopped from the loop (the session's lock)
    stop = SignalStop(lambda _name: loop.call_soon_threadsafe(ended.set))
    taken = [s for s in STOP_SIGNALS if signal.getsignal(s) is not signal.SIG_IGN]
    session = console.session
    with stop.installed(taken):
        # the token is in the address, as a notebook server prints it: the page keeps it
        print(f"torchseam console on {console.url()}  (Ctrl-C stops)", flush=True)
        try:
            await ended.wait()
            weld = _stop_weld(session, stop.signal)
            deadline = loop.time() + STOP_WAIT_S
            while session.running and loop.time() < deadline:
                await asyncio.sleep(0.05)   # the pages see it stop
            print(f"torchseam console: interrupted by {stop.signal}: "
                  f"{_weld_end(session, weld)}", file=sys.stderr, flush=True)
        finally:
            if session.running and stop.signal is None:   # cancelled, or an error
                _stop_weld(session, None)
                session.join(timeout=STOP_WAIT_S)
            await console.close()
    return stop.signal


def _stop_weld(session, by: str | None) -> int | None:
    """Stop the running weld as the page's Stop does, ``by`` named; its number (None: no weld
    running)."""
    if not session.running:
        return None
    try:
        session.stop(by)
    except RuntimeError:
        pass   # stopping already (the operator's Stop): it ends as it would
    return session.weld_id


def _weld_end(session, weld: int | None) -> str:
    """What the terminal is told of the weld a signal stopped (``weld``: its number)."""
    if weld is None:
        return "no weld was running"
    if session.running:
        return (f"weld {weld} did not stop within {STOP_WAIT_S:g} s; the console ends without "
                "it (a cell's controller stops the robot and the arc at its EGM "
                "communication timeout)")
    st = session.status()
    if st["state"] == "failed":
        return f"weld {weld} failed: {st['error']}"
    s = st["summary"] or {}
    lf = st["frame"]
    where = f" at t={lf['t']:.2f} s" if lf and lf.get("t") is not None else ""
    done = "stopped" if s.get("stopped") else "finished"
    text = f"weld {weld} {done}{where} ({s.get('frames')} frames), arc off"
    incomplete = s.get("segments_incomplete") or []
    if incomplete:
        text += "; not completed: " + "; ".join(
            f"segment {i.get('segment')} ({i.get('reason')})" for i in incomplete)
    return text
