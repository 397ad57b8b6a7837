"""The EGM link answers its controller first, whatever else arrives (issue 36).

- A foreign flood: 50 000 valid-looking ``EgmRobot`` datagrams from another local port, sent
  as fast as a process can, while the simulated controller runs against the link for 4 s:
  the controller gets at least 98 % of the replies it gets without the flood, and the kernel
  drops none of its datagrams on its own socket (the link gives the controller a socket of
  its own, connected to its address and port; everything else lands on the shared socket,
  which the link reads at a bounded rate, dropping foreign senders by address, unparsed).
- A controller that restarts on a new source port of its host is answered again after the
  port tracker's confirmation; a stream from another host (127.0.0.2 is one on loopback) is
  never taken, nor another port while the session talks.

The link runs in a process of its own, as in a cell (and as ``torchseam.robot.egm_session``
runs it); the flood in another. Figures are printed (``pytest -s``).
"""

from __future__ import annotations

import dataclasses
import json
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from torchseam.core.config import load_cell
from torchseam.robot.egm import EgmLink, latency_summary, parse_sensor
from torchseam.robot.egm.config import load_egm_config
from torchseam.robot.egm.messages import EgmHeader, EgmRobot

pytestmark = [pytest.mark.realtime,   # wall-clock timing: run alone (README's test command)
              pytest.mark.skipif(sys.platform != "linux",
                                 reason="the controller's own socket is Linux's delivery rule")]

FLOOD_N = 50_000
SESSION_S = 4.0
RT_PRIORITY = 10  # as tests/test_egm_link.py's 10 s session: the cell's set-up
CTRL = ("127.0.0.1", 6511)
FB_POS = np.array([984.0, 0.0, 624.0])
FB_QUAT = np.array([0.0, 0.0, 1.0, 0.0])
T0_US = 1_700_000_000 * 10**6


def robot_bytes(seq: int, clock_us: int, pos=FB_POS, quat=FB_QUAT) -> bytes:
    """A valid ``EgmRobot`` (RobotWare 6.07+: with ``feedBack.time``)."""
    r = EgmRobot()
    r.header.seqno, r.header.tm = seq & 0xFFFFFFFF, (4 * seq) & 0xFFFFFFFF
    r.header.mtype = EgmHeader.MSGTYPE_DATA
    r.feedBack.time.sec, r.feedBack.time.usec = divmod(int(clock_us), 10**6)
    r.feedBack.joints.joints.extend((0.0, 10.0, 10.0, 0.0, 80.0, 0.0))
    c = r.feedBack.cartesian
    c.pos.x, c.pos.y, c.pos.z = (float(v) for v in pos)
    c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = (float(v) for v in quat)
    r.motorState.state = r.motorState.MOTORS_ON
    return r.SerializeToString()


# --------------------------------------------------------------------------- processes

# The sensor: an EgmLink fed by the synthetic tracker, in a process of its own. Prints its
# address, serves until a line on stdin, then prints its counters as JSON.
_SENSOR = r"""
import dataclasses, json, sys, threading, time
from torchseam.robot.egm import EgmLink, load_egm_config, set_realtime_priority
from torchseam.robot.egm_session import Feed, run_feed
rt = int(sys.argv[2])
cfg = load_egm_config()
cfg = dataclasses.replace(cfg, mode="pathcorr", network=dataclasses.replace(
    cfg.network, port=0, controller_port=int(sys.argv[1])),
    link=dataclasses.replace(cfg.link, rt_priority=rt))
link = EgmLink(cfg).start()
stop = threading.Event()
def feed():  # below the link: it must not sit on the GIL while descheduled
    set_realtime_priority(max(0, rt - 1), "synthetic tracker")
    run_feed(link, Feed(), 600.0, None, stop.is_set)
threading.Thread(target=feed, daemon=True).start()
print("ready %s %d" % link.address, flush=True)
sys.stdin.readline()
stop.set()
time.sleep(0.05)
link.stop()
s = link.stats
d = s.as_dict()
d["realtime"] = link.realtime
d["late_log"] = [(r.wait_ms, r.work_ms, r.cpu_ms) for r in s.late_log]
print(json.dumps(d), flush=True)
"""

# The flood: FLOOD_N valid EgmRobot (a consistent stream of its own) from another local port,
# sent as fast as this process can once a line arrives on stdin; then it listens 0.3 s for
# replies and prints what it did.
_FLOOD = r"""
import json, socket, sys, time
from torchseam.robot.egm.messages import EgmHeader, EgmRobot
host, port, n, src = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
data = []
for k in range(n):
    r = EgmRobot()
    r.header.seqno, r.header.tm, r.header.mtype = 1 + k, 4 * k, EgmHeader.MSGTYPE_DATA
    r.feedBack.time.sec, r.feedBack.time.usec = divmod(int(time.time() * 1e6) + 4000 * k, 10**6)
    r.feedBack.joints.joints.extend((0.0, 10.0, 10.0, 0.0, 80.0, 0.0))
    c = r.feedBack.cartesian
    c.pos.x, c.pos.y, c.pos.z = 984.0, 0.0, 624.0
    c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = 0.0, 0.0, 1.0, 0.0
    r.motorState.state = r.motorState.MOTORS_ON
    data.append(r.SerializeToString())
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind((src, 0))
print("ready", flush=True)
sys.stdin.readline()
t0 = time.perf_counter()
addr = (host, port)
sent = 0
for d in data:
    try:
        s.sendto(d, addr)
        sent += 1
    except OSError:
        pass
took = time.perf_counter() - t0
s.settimeout(0.3)
replies = 0
try:
    while True:
        s.recvfrom(2048)
        replies += 1
except OSError:
    pass
print(json.dumps({"sent": sent, "seconds": took, "replies": replies}), flush=True)
"""


def _spawn(script: str, *args: object) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", script, *map(str, args)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def _first_line(proc: subprocess.Popen, timeout_s: float = 60.0) -> str:
    import selectors

    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout_s):
            proc.kill()
            raise TimeoutError("the child process did not start")
    line = proc.stdout.readline().strip()
    if not line:
        raise RuntimeError(f"the child process ended (exit code {proc.wait()})")
    return line


def _finish(proc: subprocess.Popen) -> dict:
    out, _ = proc.communicate("go\n", timeout=60)
    return json.loads(out.strip().splitlines()[-1])


@dataclasses.dataclass
class Run:
    sim: object         # SimStats
    link: dict          # EgmStats.as_dict() of the sensor process
    flood: dict | None  # what the flood process did
    realtime: tuple[bool, bool] = (False, False)  # (controller, link) got SCHED_FIFO

    def row(self, name: str) -> str:
        s, k = self.sim, self.link
        lat = latency_summary(s.latency_ms)
        f = (f"; flood {self.flood['sent']} sent in {self.flood['seconds']:.2f} s, "
             f"{self.flood['replies']} answered") if self.flood else ""
        return (f"  {name:<11} replies {s.replies}/{s.expected}, late {s.late_replies}, "
                f"worst reply {lat['max']:.1f} ms (p99 {lat['p99']:.2f}); link: received "
                f"{k['received']}, superseded {k['superseded']}, kernel drops controller "
                f"socket {k['kernel_dropped_controller']} / shared socket "
                f"{k['kernel_dropped_other']}, dropped {k['dropped']}, late (> 2 ms) "
                f"{k['late_replies']}, worst {k['latency_ms']['max']:.1f} ms{f}")


def run_session(robot_model, flood: bool, rt_priority: int | None = None) -> Run:
    """The simulated controller against the link for SESSION_S; with ``flood`` the flood
    starts 1 s in. Both ends ask for SCHED_FIFO ``rt_priority`` as a cell runs them (the
    flood does not: it is someone else's process); refused, they run at normal priority."""
    from torchseam.robot.sim_controller import SimController

    rt_priority = RT_PRIORITY if rt_priority is None else rt_priority
    cfg = load_egm_config()
    cfg = dataclasses.replace(cfg, sim_controller=dataclasses.replace(
        cfg.sim_controller, rt_priority=rt_priority))
    sim = SimController(cfg, robot=robot_model, tool=load_cell().tool.matrix(),
                        mode="pathcorr", bind_address=("127.0.0.1", 0))
    sensor = _spawn(_SENSOR, sim.address[1], rt_priority)
    flooder = None
    try:
        _, host, port = _first_line(sensor).split()
        sim.sensor_address = (host, int(port))
        if flood:
            flooder = _spawn(_FLOOD, host, port, FLOOD_N, "127.0.0.1")
            assert _first_line(flooder) == "ready"
        sim.start(SESSION_S)
        if flooder is not None:
            sim.wait_cycles(250)
            flooder.stdin.write("go\n")
            flooder.stdin.flush()
        sim.join(SESSION_S + 30)
        link = _finish(sensor)
        fl = _finish(flooder) if flooder is not None else None
    finally:
        sim.stop()
        for p in (sensor, flooder):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    return Run(sim.stats, link, fl, (sim.realtime, bool(link["realtime"])))


@pytest.fixture(scope="module")
def robot_model():
    from torchseam.robot.kinematics import load_irb1410

    return load_irb1410()


def test_a_foreign_flood_does_not_starve_the_controller(robot_model, record_property):
    """The bar of issue 36. Measured here (2 shared cores, load ~4, SCHED_FIFO granted), 4 s
    sessions, 4 pairs: without the flood 1000/1000 replies, 0 late, worst 0.4-0.9 ms; with it
    1000/1000, 0 late, worst 0.5-1.7 ms, 0 kernel drops on the controller's socket (43 000 -
    45 000 on the shared one; 4 700 - 6 700 flood datagrams read and dropped by address).
    The link before (one socket, every queued datagram read before answering): 961-982
    replies, 15-24 of the controller's datagrams dropped by the kernel, 18-40 late, up to
    61 ms of the link's CPU on one reply.

    Where SCHED_FIFO is refused, both ends run at normal priority and a loaded machine can
    hold the link's thread off its CPU for tens of ms whoever floods it (measured: waits up to
    45 ms, the link's own CPU per reply under 0.5 ms): there the flooded session gets a second
    try when the first missed the bar while the link's own work per reply stayed within
    ``link.late_reply_ms`` (the machine's time, not the link's, in ``EgmStats.late_log``)."""
    quiet = run_session(robot_model, flood=False)
    rows = [quiet.row("no flood")]
    realtime = all(quiet.realtime)
    late_ms = load_egm_config().link.late_reply_ms
    for attempt in range(1 if realtime else 2):
        flooded = run_session(robot_model, flood=True)
        rows.append(flooded.row("flood" if attempt == 0 else "flood again"))
        link_bounded = all(cpu <= late_ms for _, _, cpu in flooded.link["late_log"])
        if flooded.sim.replies >= 0.98 * quiet.sim.replies or not link_bounded:
            break
    sched = {True: "SCHED_FIFO", False: "normal priority"}[realtime and all(flooded.realtime)]
    print(f"\n  ({sched}, {SESSION_S:g} s at 250 Hz, {FLOOD_N} datagrams)\n" + "\n".join(rows))
    s0, s1, k = quiet.sim, flooded.sim, flooded.link
    for name, run in (("quiet", quiet), ("flood", flooded)):
        record_property(f"egm_flood_{name}_replies", run.sim.replies)
        record_property(f"egm_flood_{name}_late", run.sim.late_replies)
        record_property(f"egm_flood_{name}_worst_ms",
                        round(latency_summary(run.sim.latency_ms)["max"], 2))
    assert s0.expected == s1.expected == round(SESSION_S * 250)
    assert flooded.flood["sent"] == FLOOD_N and flooded.flood["replies"] == 0
    # the bar: >= 98 % of the replies, none of the controller's datagrams dropped
    assert s1.replies >= 0.98 * s0.replies, "\n".join(rows)
    assert k["kernel_dropped_controller"] == 0 and quiet.link["kernel_dropped"] == 0
    assert k["received"] == s1.expected  # every EgmRobot the controller sent was read
    assert set(k["dropped"]) == {"foreign_sender"}  # each flood datagram dropped unread
    # what the link read of the flood, it read at a bounded rate; the rest the kernel dropped
    read = k["dropped"]["foreign_sender"]
    assert 0 < read and read + k["kernel_dropped_other"] <= FLOOD_N
    # the link's own CPU time per reply stays small under the flood (the old link: 61 ms)
    assert all(cpu <= 4 * late_ms for _, _, cpu in k["late_log"]), k["late_log"]


# --------------------------------------------------------------------------- on the wire

def _link_for(port: int, controller_port: int, **link) -> EgmLink:
    cfg = load_egm_config()
    return EgmLink(dataclasses.replace(
        cfg, mode="pathcorr", link=dataclasses.replace(cfg.link, **link),
        network=dataclasses.replace(cfg.network, port=port, controller_port=controller_port)))


class Wire:
    """A hand-driven controller on a socket of its own: seqno +1, clock +4 ms a datagram.
    ``link`` may be given later (a link configured with this socket's port)."""

    def __init__(self, link: EgmLink | None, host: str = "127.0.0.1", seq: int = 1,
                 clock_us: int = T0_US) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.link, self.seq, self.us = link, seq - 1, clock_us - 4000

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def cycle(self, wait_s: float = 0.1) -> object | None:
        """Send the next EgmRobot; the reply (parsed) within ``wait_s``, or None. (A wait
        as long as ``session_silence_ms`` would make the controller itself look silent.)"""
        assert self.link is not None
        self.seq += 1
        self.us += 4000
        self.sock.settimeout(wait_s)
        self.sock.sendto(robot_bytes(self.seq, self.us), self.link.address)
        try:
            data = self.sock.recv(2048)
        except TimeoutError:
            return None
        msg, why = parse_sensor(data, "pathcorr")
        assert msg is not None, why
        return msg

    def close(self) -> None:
        self.sock.close()


def test_the_controller_has_a_socket_of_its_own_and_nobody_else_can_bind():
    first = Wire(None)  # its socket first: the link is configured with its port
    link = _link_for(0, first.port)
    try:
        assert link._ctrl is not None and link._ctrl.getpeername() == first.sock.getsockname()
        assert link._ctrl.getsockname() == link._shared.getsockname() == link.address
        # SO_REUSEADDR allowed the second bind for a moment only: nobody can bind it now
        for host in ("127.0.0.1", "0.0.0.0"):
            intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            intruder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            with pytest.raises(OSError):
                intruder.bind((host, link.address[1]))
            intruder.close()
        for sock in (link._ctrl, link._shared):  # both count the kernel's drops
            assert sock.getsockopt(socket.SOL_SOCKET, 40) == 1  # SO_RXQ_OVFL
    finally:
        link.stop()
        first.sock.close()


def test_port_zero_locks_onto_the_first_sender_and_gives_it_its_own_socket():
    link = _link_for(0, 0).start()
    ctrl = Wire(link)
    other = Wire(link)
    try:
        assert link._ctrl is None
        assert ctrl.cycle() is not None
        deadline = time.monotonic() + 2.0
        while link._ctrl is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert link._ctrl.getpeername() == ctrl.sock.getsockname()
        for _ in range(5):
            assert ctrl.cycle() is not None
        assert other.cycle(0.05) is None  # another port while the session talks: foreign
        s = link.stats
        assert s.received == 6 and s.dropped == {"foreign_sender": 1}
    finally:
        link.stop()
        ctrl.close()
        other.close()


def test_a_controller_back_on_a_new_port_is_answered_after_confirmation(caplog):
    """The controller stops (its socket closed), comes back from a new port of the same host:
    the first ``session_confirm - 1`` datagrams are unanswered, then it is answered again (a
    new session: the first reply holds, pathcorr a zero offset), its socket re-connected.
    Meanwhile a stream from another host (127.0.0.2), started first, is never taken; and
    once the controller talks again, neither is another port of its host."""
    old = Wire(None)
    link = _link_for(0, old.port).start()
    old.link = link
    confirm = link.config.link.session_confirm
    silence_s = link.config.link.session_silence_ms / 1e3
    try:
        link.set_correction([0.0, 0.5, 0.0])
        replies = [old.cycle() for _ in range(20)]
        assert all(r is not None for r in replies)
        assert replies[-1].pathCorr.pos.y == pytest.approx(0.5)
        clock_us, old_port = old.us, old.port
        old.close()  # the controller stops ...
        # ... a stream from another host, consistent, while the session is silent: never
        foreign = Wire(link, host="127.0.0.2", clock_us=clock_us + 10**6)
        time.sleep(silence_s + 0.05)
        assert all(foreign.cycle(0.02) is None for _ in range(3 * confirm))
        assert link.stats.controller_moves == 0
        # ... and comes back from a new port, its seqno and clock restarted
        new = Wire(link, clock_us=clock_us + 2 * 10**6)
        assert new.port != old_port
        with caplog.at_level("WARNING", logger="torchseam.robot.egm"):
            early = [new.cycle(0.02) for _ in range(confirm - 1)]
            first = new.cycle()
        assert early == [None] * (confirm - 1)
        assert first is not None and first.pathCorr.pos.y == 0.0  # new session: a hold
        link.set_correction([0.0, 0.5, 0.0])
        later = [new.cycle() for _ in range(20)]
        assert all(r is not None for r in later) and later[-1].pathCorr.pos.y == pytest.approx(0.5)
        s = link.stats
        assert s.controller_moves == 1 and s.sessions == 2 and s.holds["new_session"] == 1
        assert s.dropped["unconfirmed_port"] == confirm - 1
        assert s.dropped["foreign_sender"] == 3 * confirm  # the other host, unread
        assert link._ctrl.getpeername() == new.sock.getsockname()
        moved = [r for r in caplog.records if "moved from port" in r.getMessage()]
        assert len(moved) == 1 and str(new.port) in moved[0].getMessage()
        # the other host still gets nothing; another port of the controller's host neither
        # while the controller talks (dropped by address)
        again = Wire(link, clock_us=clock_us + 3 * 10**6)
        for _ in range(3 * confirm):
            assert foreign.cycle(0.02) is None and again.cycle(0.02) is None
            assert new.cycle() is not None
        assert link.stats.controller_moves == 1
        foreign.close()
        again.close()
    finally:
        link.stop()
        old.close()
    new.close()


def test_a_restarted_simulated_controller_is_answered_again(robot_model):
    """The simulated IRC5 stops; a new one starts on another port of the same host (seqno
    from 1, its clock the wall clock): replies again after confirmation. One on 127.0.0.2 at
    the same time never gets one."""
    from torchseam.robot.sim_controller import SimController

    cfg = load_egm_config()
    tool = load_cell().tool.matrix()
    confirm = cfg.link.session_confirm

    def sim(host: str) -> SimController:
        return SimController(cfg, robot=robot_model, tool=tool, mode="pathcorr",
                             bind_address=(host, 0))

    first = sim("127.0.0.1")
    link = _link_for(0, first.address[1]).start()
    try:
        link.set_correction([0.0, 0.2, 0.0])
        first.sensor_address = link.address
        first.start(0.4)
        first.join(5.0)
        assert first.stats.replies >= 95
        first.stop()
        time.sleep(cfg.link.session_silence_ms / 1e3 + 0.05)
        second, stranger = sim("127.0.0.1"), sim("127.0.0.2")
        for s in (second, stranger):
            s.sensor_address = link.address
        stranger.start(1.0)
        second.start(1.0)
        link.set_correction([0.0, 0.2, 0.0])
        second.join(5.0)
        stranger.join(5.0)
        a, b = second.stats, stranger.stats
        second.stop()
        stranger.stop()
        assert b.replies == 0
        assert a.replies >= a.expected - confirm - 5  # all but the unconfirmed (and stalls)
        s = link.stats
        assert s.controller_moves == 1 and s.sessions == 2
        assert s.dropped["unconfirmed_port"] == confirm - 1
        assert s.dropped["foreign_sender"] >= b.expected - 5
    finally:
        link.stop()


# --------------------------------------------------------------------------- no sockets

class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _bare(controller_port: int = 6511) -> tuple[EgmLink, Clock]:
    cfg = load_egm_config()
    clock = Clock()
    cfg = dataclasses.replace(cfg, mode="pathcorr", network=dataclasses.replace(
        cfg.network, controller_port=controller_port))
    return EgmLink(cfg, bind=False, clock=clock), clock


def test_another_port_is_not_even_parsed_while_the_session_talks():
    link, clock = _bare()
    for seq in range(1, 11):
        clock.t += 0.004
        assert link.handle_datagram(robot_bytes(seq, T0_US + 4000 * seq), CTRL) is not None
    # garbage from another port of the controller's host: foreign, not "unparseable"
    for k in range(100):
        assert link.handle_datagram(b"\xff" * (k % 7), ("127.0.0.1", 7000 + k)) is None
    # a consistent stream from one other port, right after the session's last datagram
    for k in range(10):
        clock.t += 0.004
        assert link.handle_datagram(robot_bytes(k + 1, T0_US + 10**7 + 4000 * k),
                                    ("127.0.0.1", 7000)) is None
    assert link.stats.dropped == {"foreign_sender": 110}
    assert link.stats.controller_moves == 0


def test_a_new_port_needs_silence_consistency_and_a_fresh_clock():
    link, clock = _bare()
    confirm = link.config.link.session_confirm
    for seq in range(1, 51):
        clock.t += 0.004
        assert link.handle_datagram(robot_bytes(seq, T0_US + 4000 * seq), CTRL) is not None
    clock.t += link.config.link.session_silence_ms / 1e3 + 0.01
    new = ("127.0.0.1", 40000)
    # the session's own datagrams again, from a new port: replays, never a restart
    for seq in range(1, 3 * confirm):
        clock.t += 0.004
        assert link.handle_datagram(robot_bytes(seq, T0_US + 4000 * seq), new) is None
    assert link.stats.dropped == {"replayed": 3 * confirm - 1}
    # inconsistent datagrams (the clock running backwards, seqnos repeating) do not confirm
    for k in range(3 * confirm):
        clock.t += 0.004
        out = link.handle_datagram(robot_bytes(7, T0_US + 10**8 - 4000 * k), new)
        assert out is None
    assert link.stats.controller_moves == 0
    # another host, consistent: never
    for k in range(3 * confirm):
        clock.t += 0.004
        assert link.handle_datagram(robot_bytes(k + 1, T0_US + 2 * 10**8 + 4000 * k),
                                    ("127.0.0.2", 40000)) is None
    # a consistent stream from a fresh port: the confirm-th datagram is answered
    other = ("127.0.0.1", 40001)
    out = []
    for k in range(confirm + 3):
        clock.t += 0.004
        out.append(link.handle_datagram(robot_bytes(k + 1, T0_US + 3 * 10**8 + 4000 * k),
                                        other))
    assert out[:confirm - 1] == [None] * (confirm - 1)
    assert all(o is not None for o in out[confirm - 1:])
    s = link.stats
    assert s.controller_moves == 1 and s.sessions == 2 and s.holds["new_session"] == 1
    # from now on the old port is foreign while the new one talks
    clock.t += 0.004
    assert link.handle_datagram(robot_bytes(51, T0_US + 4000 * 51), CTRL) is None
    assert link.stats.dropped["foreign_sender"] == 3 * confirm + 1


def test_the_first_reply_after_a_move_holds_and_the_hooks_see_it():
    """``on_robot`` sees the confirming datagram (and returning True there starts the new
    motion as before); ``on_reply`` sees every reply."""
    cfg = load_egm_config()
    cfg = dataclasses.replace(cfg, mode="pose")
    clock = Clock()
    seen: list[int] = []
    replies: list[object] = []
    link = EgmLink(cfg, bind=False, clock=clock,
                   on_robot=lambda r, t: seen.append(r.header.seqno) or False,
                   on_reply=replies.append)
    for seq in range(1, 6):
        clock.t += 0.004
        assert link.handle_datagram(robot_bytes(seq, T0_US + 4000 * seq), CTRL) is not None
    link.set_target(FB_POS + [1.0, 0.0, 0.0], FB_QUAT)
    clock.t += 0.004
    assert link.handle_datagram(robot_bytes(6, T0_US + 4000 * 6), CTRL) is not None
    clock.t += 1.0
    moved_to = FB_POS + [0.0, 30.0, 0.0]  # RAPID moved the robot meanwhile
    out = None
    for k in range(cfg.link.session_confirm):
        clock.t += 0.004
        out = link.handle_datagram(robot_bytes(k + 1, T0_US + 10**7 + 4000 * k, moved_to),
                                   ("127.0.0.1", 40000))
    assert out is not None
    msg, _ = parse_sensor(out, "pose")
    c = msg.planned.cartesian
    np.testing.assert_allclose([c.pos.x, c.pos.y, c.pos.z], moved_to)  # holds where it is
    assert seen == [1, 2, 3, 4, 5, 6, cfg.link.session_confirm]
    assert len(replies) == 7 and link.stats.holds["new_session"] == 1
    assert link.stats.sessions == 2
