"""A complete EGM session on loopback: the simulated controller against the sensor link, fed
by a synthetic tracker. Used by ``torchseam robot sim-controller --sensor``, ``bench/egm.py``
and the tests.

By default the sensor side (link + feed) runs in a child process, as it would in a cell where
controller and sensor are different machines: in one process the two would share the GIL, and a
thread that holds it while the OS has descheduled it delays the other side's datagrams by whole
time slices. The child imports no torch, so it starts in well under a second.

This module imports neither torch nor the robot model at import time: the sensor's child
process imports it, and only it.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import multiprocessing as mp
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from torchseam.robot.egm import (
    EgmConfig,
    EgmError,
    EgmLink,
    EgmStats,
    latency_summary,
    set_realtime_priority,
)

_CHILD_TIMEOUT_S = 60.0  # spawning a Python child on a loaded 2-core machine takes seconds


@dataclass(frozen=True)
class Feed:
    """Synthetic tracker output: ``rate_hz`` measurements a second, each ``delay_ms`` old.

    Pathcorr: offsets ``amplitude_mm * sin(2 pi wave_hz t)`` across the path (y of the path
    frame). Pose: the start TCP pose moved by the same wave along the base y axis.
    """

    rate_hz: float = 25.0
    amplitude_mm: float = 1.0
    wave_hz: float = 0.5
    delay_ms: float = 20.0


def run_feed(link: EgmLink, feed: Feed, duration_s: float,
             start_pose: tuple[np.ndarray, np.ndarray] | None, stop: Any = None) -> int:
    """Feed ``link`` for ``duration_s`` (or until ``stop()`` is true); returns measurements
    given. ``start_pose``, the TCP's ``(position mm, quaternion w x y z)``, is needed in pose
    mode."""
    if link.mode == "pose" and start_pose is None:
        raise EgmError("a pose-mode feed needs the start TCP pose")
    t0 = time.monotonic()
    period = 1.0 / feed.rate_hz
    k = 0
    while time.monotonic() - t0 < duration_s and not (stop is not None and stop()):
        now = time.monotonic()
        wave = feed.amplitude_mm * math.sin(2 * math.pi * feed.wave_hz * (now - t0))
        measured = now - feed.delay_ms / 1e3
        if link.mode == "pathcorr":
            link.set_correction([0.0, wave, 0.0], measured_at=measured)
        else:
            assert start_pose is not None
            link.set_target(start_pose[0] + [0.0, wave, 0.0], start_pose[1],
                            measured_at=measured)
        k += 1
        time.sleep(max(0.0, t0 + k * period - time.monotonic()))
    return k


def _sensor_main(conn: Any, config: EgmConfig, feed: Feed, duration_s: float,
                 start_pose: tuple[np.ndarray, np.ndarray]) -> None:
    """Child process: run an :class:`EgmLink` and its feed; report the stats over ``conn``."""
    try:
        link = EgmLink(config)
    except Exception as e:
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    # everything imported so far lives as long as the process: keep it out of the cyclic
    # collector, whose full passes would otherwise stall the 4 ms loop for ~25 ms
    gc.freeze()
    try:
        link.start()
        if config.link.rt_priority > 1:  # the feed must not sit on the GIL while descheduled
            set_realtime_priority(config.link.rt_priority - 1, "synthetic tracker")
        conn.send(("ready", link.address))
        if not conn.poll(_CHILD_TIMEOUT_S) or conn.recv() != "go":
            return
        run_feed(link, feed, duration_s + 5.0, start_pose, stop=conn.poll)
        conn.recv()  # "stop": the controller has finished
        time.sleep(0.05)  # let the last reply leave
    except Exception as e:
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    finally:
        link.stop()
    conn.send(("stats", (link.stats, link.realtime)))


@dataclass
class SessionResult:
    """Outcome of :func:`loopback_session`: both sides' counters and the run's set-up."""

    mode: str
    duration_s: float
    rate_hz: float
    sim: Any  # SimStats
    link: EgmStats
    realtime: tuple[bool, bool] = (False, False)  # (controller, sensor) got SCHED_FIFO

    def table(self) -> str:
        """A plain-text summary (latencies in ms)."""
        s, k = self.sim, self.link
        lat = latency_summary(s.latency_ms)
        proc = k.latency_summary()
        jit = latency_summary(np.abs(np.fromiter(s.jitter_ms, float)))
        comp = latency_summary(s.compute_ms)

        def row(name: str, d: dict[str, float]) -> str:
            return f"  {name:<36} {d['p50']:8.3f} {d['p99']:8.3f} {d['max']:8.3f}"

        rt = {True: "real-time", False: "normal"}
        lines = [
            f"EGM loopback session: mode {self.mode}, {self.rate_hz:g} Hz, {self.duration_s:g} s; "
            f"controller {rt[self.realtime[0]]}, sensor {rt[self.realtime[1]]} scheduling",
            f"  {'(ms)':<36} {'p50':>8} {'p99':>8} {'max':>8}",
            row("reply latency, controller side", lat),
            row("reply latency, sensor side", proc),
            row("cycle jitter |start - schedule|", jit),
            row("controller send (start -> left)", latency_summary(s.send_ms)),
            row("controller model update", comp),
        ]
        lines += [
            f"  controller: cycles {s.cycles}, EgmRobot sent {s.sent}, replies {s.replies}, "
            f"late replies {s.late_replies}, extra replies {s.extra_replies}, "
            f"overruns {s.overruns}, rejected {dict(s.rejected)}, faults {dict(s.faults)}, "
            f"largest lag {s.max_lag_mm:.3f} mm"
            + (f", sent without a kernel time stamp {s.unstamped}" if s.unstamped else ""),
            f"  sensor: received {k.received}, sent {k.sent}, commands {k.commands}, "
            f"holds {dict(k.holds)}, refused {dict(k.refused)}, dropped {dict(k.dropped)}, "
            f"superseded {k.superseded}, late (> link.late_reply_ms) {k.late_replies}",
        ]
        if k.late_log:
            w = np.array([(r.wait_ms, r.work_ms, r.cpu_ms) for r in k.late_log])
            p50, mx = np.median(w, axis=0), w.max(axis=0)
            lines.append(
                f"  sensor's late replies ({len(w)}), ms p50/max: waiting to run "
                f"{p50[0]:.2f}/{mx[0]:.2f}, working {p50[1]:.2f}/{mx[1]:.2f}, of it on the CPU "
                f"{p50[2]:.2f}/{mx[2]:.2f}")
        return "\n".join(lines)


def loopback_session(config: EgmConfig, duration_s: float = 10.0, *, robot: Any,
                     tool: np.ndarray, mode: str | None = None, feed: Feed | None = None,
                     sensor_process: bool = True,
                     sim_kwargs: dict[str, Any] | None = None) -> SessionResult:
    """Run the simulated controller against an :class:`EgmLink` on loopback (ephemeral ports)
    for ``duration_s``, the link fed by :func:`run_feed`.

    Args:
        config: EGM configuration (the caller reads it, e.g. with
            :func:`~torchseam.robot.egm.config.load_egm_config`); its ports are not used.
        duration_s: session length, s (cycles = duration x ``sim_controller.rate_hz``).
        robot: the simulated controller's kinematic model, an
            :class:`~torchseam.robot.kinematics.IRB1410` (``load_irb1410()``: the shipped one).
        tool: TCP pose in the flange frame, 4x4 mm (the cell's torch:
            ``load_cell().tool.matrix()``).
        mode: ``pose`` or ``pathcorr`` (default the config's).
        feed: the synthetic tracker.
        sensor_process: run the link and its feed in a child process (default) or in threads
            of this one.
        sim_kwargs: extra arguments of :class:`~torchseam.robot.sim_controller.SimController`.

    The cyclic garbage collector of this process is paused while the session runs (restored
    after); the sensor's child process freezes its start-up objects out of it instead.
    """
    from torchseam.core.transforms import matrix_to_quat
    from torchseam.robot.sim_controller import SimController

    mode = mode or config.mode
    feed = feed or Feed()
    net = config.network
    sim = SimController(config, robot=robot, tool=tool, mode=mode,
                        sensor_address=(net.host, 0), bind_address=(net.controller_host, 0),
                        **(sim_kwargs or {}))
    link_cfg = dataclasses.replace(config, mode=mode, network=dataclasses.replace(
        net, port=0, controller_port=sim.address[1]))
    T = sim.tcp_pose()
    start_pose = (T[:3, 3].copy(), matrix_to_quat(T[:3, :3]))
    # a full pass of the cyclic garbage collector in a process that has torch loaded takes
    # ~0.3 s, long enough to stall the simulated controller mid-cycle: pause it for the session
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        if sensor_process:
            link_stats, link_rt = _run_with_child(sim, link_cfg, feed, duration_s, start_pose)
        else:
            link_stats, link_rt = _run_in_threads(sim, link_cfg, feed, duration_s, start_pose)
    finally:
        sim.stop()
        if gc_was_enabled:
            gc.enable()
    return SessionResult(mode, duration_s, config.sim_controller.rate_hz, sim.stats,
                         link_stats, (sim.realtime, link_rt))


def _run_in_threads(sim: Any, cfg: EgmConfig, feed: Feed, duration_s: float,
                    start_pose: tuple[np.ndarray, np.ndarray]) -> tuple[EgmStats, bool]:
    with EgmLink(cfg) as link:
        sim.sensor_address = link.address
        sim.start(duration_s)
        run_feed(link, feed, duration_s + 5.0, start_pose, stop=lambda: not sim.running)
        sim.join()
        return link.stats, link.realtime


def _run_with_child(sim: Any, cfg: EgmConfig, feed: Feed, duration_s: float,
                    start_pose: tuple[np.ndarray, np.ndarray]) -> tuple[EgmStats, bool]:
    ctx = mp.get_context("spawn")  # never fork a process that holds torch's thread pools
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_sensor_main, name="egm-sensor",
                       args=(child, cfg, feed, duration_s, start_pose), daemon=True)
    proc.start()
    try:
        kind, value = _receive(parent, proc)
        sim.sensor_address = tuple(value)
        sim.start(duration_s)
        parent.send("go")
        sim.join()
        parent.send("stop")
        kind, value = _receive(parent, proc)
        return value
    finally:
        proc.join(timeout=5.0)
        if proc.is_alive():
            proc.terminate()
            proc.join(timeout=5.0)


def _receive(conn: Any, proc: Any) -> tuple[str, Any]:
    end = time.monotonic() + _CHILD_TIMEOUT_S
    while not conn.poll(0.1):
        if not proc.is_alive():
            raise EgmError(f"the sensor process ended (exit code {proc.exitcode}); a script that "
                           "runs a session needs an `if __name__ == \"__main__\":` guard")
        if time.monotonic() > end:
            raise EgmError(f"the sensor process did not answer within {_CHILD_TIMEOUT_S:g} s")
    try:
        kind, value = conn.recv()
    except EOFError:
        raise EgmError(f"the sensor process ended (exit code {proc.exitcode})") from None
    if kind == "error":
        raise EgmError(f"the sensor process failed: {value}")
    return kind, value
