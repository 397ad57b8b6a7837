"""EGM loopback session statistics: the simulated IRC5 against the sensor link at 250 Hz.

    .venv/bin/python bench/egm.py [--duration 10] [--modes pathcorr,pose] [--rt 0,10]

For each mode and scheduling (``--rt``: SCHED_FIFO priorities, 0 = normal; a refused priority
runs normal, and the table says so) it runs ``torchseam.robot.egm_session.loopback_session``:
the controller in this process, the sensor (EgmLink + a synthetic 25 Hz tracker) in a child
process. Columns, in ms: reply latency seen by the controller (EgmRobot sent -> reply in the
kernel, both time stamps from the kernel clock) p50 / p99 / max; the sensor's own time from
kernel arrival to reply sent (p50 / p99); cycle jitter |start - schedule| p50 / p99 / max.
Counts: late replies (later than one 4 ms period or missing), sensor-side superseded
datagrams. The machine's load average and the CPU time the hypervisor stole during each run
are printed with it: timings on a shared machine mean little without them.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

import numpy as np

from torchseam.core.config import load_cell
from torchseam.robot.egm import latency_summary
from torchseam.robot.egm.config import load_egm_config
from torchseam.robot.egm_session import loopback_session
from torchseam.robot.kinematics import load_irb1410


def _steal_ticks() -> int | None:
    """CPU time stolen by the hypervisor so far, in USER_HZ ticks (Linux), else None."""
    try:
        with open("/proc/stat") as f:
            return int(f.readline().split()[8])
    except (OSError, IndexError, ValueError):
        return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per run (default 10)")
    ap.add_argument("--modes", default="pathcorr,pose", help="comma-separated EGM modes")
    ap.add_argument("--rt", default="0,10",
                    help="comma-separated SCHED_FIFO priorities to run with (0 = normal)")
    args = ap.parse_args()
    cfg0 = load_egm_config()
    robot, tool = load_irb1410(), load_cell().tool.matrix()
    hz = cfg0.sim_controller.rate_hz
    print(f"EGM loopback bench: {hz:g} Hz, {args.duration:g} s per run, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, {platform.platform()}")
    head = (f"{'mode':<9} {'sched':<9} {'cycles':>6} {'late':>5} "
            f"{'lat p50':>8} {'p99':>7} {'max':>7} {'sens p50':>9} {'p99':>7} "
            f"{'jit p50':>8} {'p99':>7} {'max':>7} {'superseded':>10} {'load':>5} {'steal':>6}")
    rows, tables = [], []
    for mode in args.modes.split(","):
        for prio in (int(p) for p in args.rt.split(",")):
            cfg = dataclasses.replace(
                cfg0, link=dataclasses.replace(cfg0.link, rt_priority=prio),
                sim_controller=dataclasses.replace(cfg0.sim_controller, rt_priority=prio))
            load = os.getloadavg()[0]
            s0 = _steal_ticks()
            t0 = time.perf_counter()
            r = loopback_session(cfg, args.duration, robot=robot, tool=tool, mode=mode)
            wall = time.perf_counter() - t0
            s1 = _steal_ticks()
            steal = "n/a" if s0 is None or s1 is None else f"{(s1 - s0) * 10 / wall:.0f}"
            lat = latency_summary(r.sim.latency_ms)
            sen = r.link.latency_summary()
            jit = latency_summary(np.abs(np.fromiter(r.sim.jitter_ms, float)))
            sched = ("fifo " + str(prio)) if all(r.realtime) else "normal"
            rows.append(f"{mode:<9} {sched:<9} {r.sim.cycles:>6} {r.sim.late_replies:>5} "
                        f"{lat['p50']:>8.3f} {lat['p99']:>7.3f} {lat['max']:>7.3f} "
                        f"{sen['p50']:>9.3f} {sen['p99']:>7.3f} "
                        f"{jit['p50']:>8.3f} {jit['p99']:>7.3f} {jit['max']:>7.3f} "
                        f"{r.link.superseded:>10} {load:>5.1f} {steal:>6}")
            tables.append(r.table())
    print("\n".join(tables))
    print("\nlatencies in ms; load: 1-min load average before the run; steal: ms of CPU the "
          "hypervisor took per s of the run")
    print(head)
    print("\n".join(rows))


if __name__ == "__main__":
    main()
