"""``torchseam robot sim-controller``: the simulated IRC5 EGM controller on the command line.

Registered into the ``torchseam robot`` group by ``torchseam/robot/cli.py`` through
:func:`register`.

Examples::

    # controller only, streaming to a sensor (e.g. the live loop) on 127.0.0.1:6510
    torchseam robot sim-controller --duration 30
    # a whole loopback session: controller + EgmLink + a synthetic tracker, then the stats
    torchseam robot sim-controller --sensor --duration 10 --mode pathcorr
"""

from __future__ import annotations

import argparse
import dataclasses
import ipaddress
import sys
import time
from typing import Any

from torchseam.core.config import ConfigError
from torchseam.robot.egm import MODES, latency_summary, load_egm_config


def register(robot_subparsers: Any) -> None:
    """Add ``sim-controller`` to the ``torchseam robot`` sub-parsers."""
    p = robot_subparsers.add_parser(
        "sim-controller",
        help="simulated IRC5 controller speaking ABB EGM over UDP (IRB 1410 model)",
        description="Run a simulated IRC5 controller that streams EgmRobot to an EGM sensor "
                    "and moves a simulated IRB 1410 by its replies; prints the statistics at "
                    "the end (latencies in ms).")
    p.add_argument("--config", default=None, metavar="YAML",
                   help="EGM configuration (default configs/egm.yaml)")
    p.add_argument("--mode", choices=MODES, default=None,
                   help="pose (EgmSensor) or pathcorr (EgmSensorPathCorr); default: config")
    p.add_argument("--host", default=None,
                   help="the sensor's address (default: network.host of the config)")
    p.add_argument("--port", type=int, default=None,
                   help="the sensor's UDP port (default: network.port)")
    p.add_argument("--bind-host", default=None,
                   help="the controller's own address (default: network.controller_host)")
    p.add_argument("--bind-port", type=int, default=None,
                   help="the controller's own port (default: network.controller_port)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="EgmRobot rate (default: sim_controller.rate_hz, 250)")
    p.add_argument("--duration", type=float, default=10.0, metavar="S",
                   help="seconds to run; 0 runs until Ctrl-C (default 10)")
    p.add_argument("--sensor", action="store_true",
                   help="also run the EGM sensor (EgmLink fed by a synthetic tracker) on "
                        "loopback, in a child process; ports are then picked by the system")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow a sensor address that is not loopback")
    p.add_argument("--rt-priority", type=int, default=None, metavar="N",
                   help="SCHED_FIFO priority 1-99 for the controller's cycle thread (and the "
                        "sensor's with --sensor); 0: normal scheduling (default: config)")
    p.set_defaults(func=run_sim_controller)


def run_sim_controller(args: argparse.Namespace) -> int:
    """Entry point of ``torchseam robot sim-controller``."""
    from torchseam.core.config import load_cell
    from torchseam.robot.egm_session import loopback_session
    from torchseam.robot.kinematics import load_irb1410
    from torchseam.robot.sim_controller import SimController

    config = load_egm_config(args.config)
    net = config.network
    if args.rate is not None:
        if not 1.0 <= args.rate <= 1000.0:
            raise ConfigError(f"--rate: expected 1..1000 Hz, got {args.rate:g}")
        config = dataclasses.replace(config, sim_controller=dataclasses.replace(
            config.sim_controller, rate_hz=float(args.rate)))
    if args.rt_priority is not None:
        if not 0 <= args.rt_priority <= 99:
            raise ConfigError(f"--rt-priority: expected 0..99, got {args.rt_priority}")
        config = dataclasses.replace(
            config, link=dataclasses.replace(config.link, rt_priority=args.rt_priority),
            sim_controller=dataclasses.replace(config.sim_controller,
                                               rt_priority=args.rt_priority))
    if args.duration < 0:
        raise ConfigError(f"--duration: expected seconds >= 0, got {args.duration:g}")
    mode = args.mode or config.mode
    robot, tool = load_irb1410(), load_cell().tool.matrix()  # the arm and the cell's torch
    if args.sensor:
        if args.duration == 0:
            raise ConfigError("--sensor needs a --duration > 0")
        result = loopback_session(config, args.duration, robot=robot, tool=tool, mode=mode)
        print(result.table())
        return 0
    host = args.host or net.host
    port = net.port if args.port is None else args.port
    if not 1 <= port <= 65535:
        raise ConfigError(f"--port: expected the sensor's port 1..65535, got {port}")
    bind = (args.bind_host or net.controller_host,
            net.controller_port if args.bind_port is None else args.bind_port)
    for name, value in (("--host", host), ("--bind-host", bind[0])):
        try:
            ipaddress.ip_address(value)
        except ValueError:
            raise ConfigError(f"{name}: not an IP address: {value!r}") from None
    if not ipaddress.ip_address(host).is_loopback and not args.allow_remote:
        raise ConfigError(f"--host {host} is not loopback: pass --allow-remote to stream a "
                          "simulated robot onto a network")
    sim = SimController(config, robot=robot, tool=tool, mode=mode, sensor_address=(host, port),
                        bind_address=bind)
    print(f"simulated IRC5: {mode}, {config.sim_controller.rate_hz:g} Hz, EgmRobot from "
          f"{sim.address[0]}:{sim.address[1]} to {host}:{port}", file=sys.stderr)
    t0 = time.monotonic()
    rc = 0
    try:
        sim.run(args.duration or None)
    except KeyboardInterrupt:
        rc = 130
    finally:
        sim.stop()
    print(format_sim_stats(sim.stats, mode, config.sim_controller.rate_hz,
                           time.monotonic() - t0))
    return rc


def format_sim_stats(stats: Any, mode: str, rate_hz: float, duration_s: float) -> str:
    """The simulated controller's statistics as a table (ms)."""
    rows = [("reply latency", latency_summary(stats.latency_ms)),
            ("cycle jitter", latency_summary(abs(x) for x in stats.jitter_ms)),
            ("model update", latency_summary(stats.compute_ms))]
    lines = [f"simulated IRC5: mode {mode}, {rate_hz:g} Hz, {duration_s:.1f} s",
             f"  {'(ms)':<16} {'p50':>8} {'p99':>8} {'max':>8}"]
    lines += [f"  {name:<16} {d['p50']:8.3f} {d['p99']:8.3f} {d['max']:8.3f}" for name, d in rows]
    lines.append(f"  cycles {stats.cycles}, EgmRobot sent {stats.sent}, replies {stats.replies}, "
                 f"late replies {stats.late_replies}, extra replies {stats.extra_replies}, "
                 f"rejected {dict(stats.rejected)}, overruns {stats.overruns}, "
                 f"send errors {stats.send_errors}")
    return "\n".join(lines)
