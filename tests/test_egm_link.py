"""The EGM sensor link: safety refusals, watchdog, datagram hygiene, fault injection, a 250 Hz
loopback session against the simulated controller, and a fuzz test of the datagram parser."""

from __future__ import annotations

import dataclasses
import logging
import math
import random
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchseam.core.config import CONFIG_DIR, ConfigError, load_cell
from torchseam.robot.egm import EgmError, EgmLink, latency_summary, parse_robot, parse_sensor
from torchseam.robot.egm.config import egm_config_from_dict, load_egm_config
from torchseam.robot.egm.messages import EgmHeader, EgmRobot, EgmSensor
from torchseam.robot.egm_session import Feed, loopback_session, run_feed

pytestmark = pytest.mark.realtime  # wall-clock timing: run alone (README's test command)

CTRL = ("127.0.0.1", 6511)  # the shipped config's controller address
FB_POS = np.array([984.0, 0.0, 624.0])  # fed-back TCP of the unit tests, mm
FB_QUAT = np.array([0.0, 0.0, 1.0, 0.0])  # torch pointing down


class Clock:
    """A hand-driven monotonic clock, seconds."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


T0_US = 1_700_000_000 * 10**6  # the controller clock (feedBack.time) at seqno 0, us


def robot_bytes(seq: int, pos=FB_POS, quat=FB_QUAT, mtype: int = EgmHeader.MSGTYPE_DATA,
                joints=(0.0, 10.0, 10.0, 0.0, 80.0, 0.0), clock_us: int | None = None) -> bytes:
    """An ``EgmRobot`` as RobotWare 6.07+ sends it: its clock ``feedBack.time`` (the link
    refuses datagrams without one, issue 25) runs 4 ms a seqno unless ``clock_us`` is given."""
    r = EgmRobot()
    r.header.seqno, r.header.tm, r.header.mtype = seq, (4 * seq) & 0xFFFFFFFF, mtype
    us = T0_US + 4000 * seq if clock_us is None else clock_us
    r.feedBack.time.sec, r.feedBack.time.usec = divmod(us, 10**6)
    r.feedBack.joints.joints.extend(joints)
    c = r.feedBack.cartesian
    c.pos.x, c.pos.y, c.pos.z = (float(v) for v in pos)
    c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = (float(v) for v in quat)
    r.motorState.state = r.motorState.MOTORS_ON
    return r.SerializeToString()


def make_link(mode: str = "pathcorr", gate=None, clock: Clock | None = None,
              latency_samples: int = 1000, **safety) -> EgmLink:
    cfg = load_egm_config()
    cfg = dataclasses.replace(cfg, mode=mode, safety=dataclasses.replace(cfg.safety, **safety),
                              link=dataclasses.replace(cfg.link,
                                                       latency_samples=latency_samples))
    return EgmLink(cfg, bind=False, gate=gate, clock=clock or Clock())


class Controller:
    """Drives a socket-free link like a controller at 250 Hz on a fake clock."""

    def __init__(self, link: EgmLink, clock: Clock) -> None:
        self.link, self.clock, self.seq = link, clock, 0

    def cycle(self, pos=FB_POS, quat=FB_QUAT):
        self.clock.t += 0.004
        self.seq += 1
        out = self.link.handle_datagram(robot_bytes(self.seq, pos, quat), CTRL)
        assert out is not None, "a valid EgmRobot must be answered"
        msg, why = parse_sensor(out, self.link.mode)
        assert msg is not None, why
        return msg


def offset(msg) -> list[float]:
    p = msg.pathCorr.pos
    return [p.x, p.y, p.z]


def pose_of(msg) -> tuple[np.ndarray, np.ndarray]:
    c = msg.planned.cartesian
    return (np.array([c.pos.x, c.pos.y, c.pos.z]),
            np.array([c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3]))


# --------------------------------------------------------------------------- configuration

def test_config_loads_and_bad_fields_are_named():
    cfg = load_egm_config()
    assert (cfg.network.host, cfg.network.port, cfg.network.controller_port) == (
        "127.0.0.1", 6510, 6511)
    assert cfg.network.is_loopback and cfg.mode in ("pose", "pathcorr")
    assert cfg.sim_controller.period_s == pytest.approx(0.004)
    raw = yaml.safe_load((CONFIG_DIR / "egm.yaml").read_text())
    for patch, where in [({"mode": "position"}, "mode"),
                         ({"network": {**raw["network"], "host": "robot.local"}},
                          "network.host"),
                         ({"network": {**raw["network"], "port": 70000}}, "network.port"),
                         ({"safety": {**raw["safety"], "max_step_mm": -1}},
                          "safety.max_step_mm"),
                         ({"safety": {**raw["safety"], "watchdog": 5}}, "safety.watchdog"),
                         ({"sim_controller": {**raw["sim_controller"], "rate_hz": 0}},
                          "sim_controller.rate_hz")]:
        with pytest.raises(ConfigError, match=where.replace(".", r"\.")):
            egm_config_from_dict({**raw, **patch})


# --------------------------------------------------------------------------- path correction

def test_pathcorr_replies_carry_offset_age_and_header():
    clock = Clock()
    link = make_link(clock=clock)
    ctl = Controller(link, clock)
    first = ctl.cycle()
    assert offset(first) == [0.0, 0.0, 0.0] and first.pathCorr.age == 0  # no measurement: hold
    assert link.stats.holds == {"no_measurement": 1}
    assert link.set_correction([0.0, 0.8, -0.3], measured_at=clock.t - 0.030).ok
    msg = ctl.cycle()
    assert offset(msg) == pytest.approx([0.0, 0.8, -0.3])
    assert msg.pathCorr.age == 34  # 30 ms old when given + one 4 ms cycle
    assert msg.header.mtype == EgmHeader.MSGTYPE_PATH_CORRECTION
    assert msg.header.seqno == first.header.seqno + 1
    assert msg.header.tm - first.header.tm == 4
    assert link.stats.commands == 1


def _gate(p: np.ndarray, q: np.ndarray) -> tuple[bool, str]:
    if p[0] < 0:
        raise RuntimeError("IK exploded")
    return (p[0] < 1500.0, f"x = {p[0]:.0f} mm is beyond the reach")


GOOD_POSE = (FB_POS, FB_QUAT)


@pytest.mark.parametrize("reason, bad", [
    ("non_finite", dict(offset_mm=[0.0, math.nan, 0.0])),
    ("non_finite", dict(offset_mm=[math.inf, 0.0, 0.0])),
    ("non_finite", dict(offset_mm=[0.0, 0.5, 0.0], pose=(FB_POS + [0, math.nan, 0], FB_QUAT))),
    ("correction_too_large", dict(offset_mm=[0.0, 10.5, 0.0])),
    ("stale", dict(offset_mm=[0.0, 0.6, 0.0], age_s=0.150)),
    ("future_timestamp", dict(offset_mm=[0.0, 0.6, 0.0], age_s=-0.050)),
    ("gate", dict(offset_mm=[0.0, 0.6, 0.0], pose=(FB_POS + [900.0, 0, 0], FB_QUAT))),
    ("gate_error", dict(offset_mm=[0.0, 0.6, 0.0], pose=(-FB_POS, FB_QUAT))),
    ("no_gate_pose", dict(offset_mm=[0.0, 0.6, 0.0], pose=None)),
    ("bad_quaternion", dict(offset_mm=[0.0, 0.6, 0.0], pose=(FB_POS, FB_QUAT * 1.1))),
    ("step_too_large", dict(offset_mm=[0.0, 3.0, 0.0])),  # 2.5 mm from the last sent
])
def test_refused_corrections_never_reach_the_wire(reason, bad, caplog):
    clock = Clock()
    link = make_link(gate=_gate, clock=clock)
    ctl = Controller(link, clock)
    assert link.set_correction([0.0, 0.5, 0.0], pose=GOOD_POSE).ok
    assert offset(ctl.cycle()) == [0.0, 0.5, 0.0]
    with caplog.at_level(logging.WARNING, logger="torchseam.robot.egm"):
        v = link.set_correction(bad["offset_mm"], measured_at=clock.t - bad.get("age_s", 0.0),
                                pose=bad.get("pose", GOOD_POSE))
        replies = [ctl.cycle() for _ in range(3)]
    if reason == "step_too_large":
        assert v.ok  # passes the static checks; refused when the reply is built
    else:
        assert not v.ok and v.reason == reason and v.detail
    for msg in replies:  # the last vetted offset holds; the bad one never goes out
        assert offset(msg) == [0.0, 0.5, 0.0]
    stats = link.stats
    assert stats.refused == {reason: 1}  # one refusal per measurement, not per cycle
    assert sum(reason in r.getMessage() for r in caplog.records) == 1
    if reason == "step_too_large":  # the refused measurement is current: the link holds
        assert stats.commands == 1 and stats.holds == {"refused": 3}
    else:  # never stored: the previous measurement stays in force
        assert stats.commands == 4 and not stats.holds


def test_a_measurement_going_stale_is_held_with_age_zero(caplog):
    clock = Clock()
    link = make_link(clock=clock)
    ctl = Controller(link, clock)
    link.set_correction([0.0, 1.0, 0.0], measured_at=clock.t - 0.020)
    with caplog.at_level(logging.WARNING, logger="torchseam.robot.egm"):
        msgs = [ctl.cycle() for _ in range(30)]  # 120 ms, watchdog (200 ms) not yet
    ages = [m.pathCorr.age for m in msgs]
    assert all(offset(m) == [0.0, 1.0, 0.0] for m in msgs)
    fresh = [a for a in ages if a > 0]
    assert max(fresh) <= 100 and ages[-1] == 0  # never older than max_age_ms
    assert link.stats.refused == {"stale": 1} and link.stats.holds["refused"] == ages.count(0)
    assert [r.getMessage().count("stale") for r in caplog.records] == [1]


def test_watchdog_holds_when_measurements_stop_and_resumes(caplog):
    clock = Clock()
    link = make_link(clock=clock, max_age_ms=1000.0)  # isolate the watchdog (200 ms)
    ctl = Controller(link, clock)
    link.set_correction([0.0, 1.5, 0.0])
    with caplog.at_level(logging.WARNING, logger="torchseam.robot.egm"):
        msgs = [ctl.cycle() for _ in range(75)]  # 300 ms without a measurement
    assert link.holding and link.stats.watchdog_trips == 1
    ages = [m.pathCorr.age for m in msgs]
    assert all(a > 0 for a in ages[:49]) and not any(ages[51:])  # holds from ~200 ms on
    assert ages.count(0) == link.stats.holds["watchdog"]
    assert all(offset(m) == [0.0, 1.5, 0.0] for m in msgs)  # no jump back onto the path
    assert any("watchdog" in r.getMessage() for r in caplog.records)
    link.set_correction([0.0, 1.7, 0.0])
    assert offset(ctl.cycle()) == pytest.approx([0.0, 1.7, 0.0]) and not link.holding
    assert link.stats.watchdog_trips == 1


def test_cleared_measurement_holds():
    clock = Clock()
    link = make_link(clock=clock)
    ctl = Controller(link, clock)
    link.set_correction([0.0, 0.4, 0.0])
    ctl.cycle()
    link.clear_measurement()
    assert offset(ctl.cycle()) == pytest.approx([0.0, 0.4, 0.0])
    assert link.stats.holds["no_measurement"] == 1


def test_wrong_mode_calls_are_errors():
    with pytest.raises(EgmError, match="set_correction"):
        make_link("pathcorr").set_target(FB_POS, FB_QUAT)
    with pytest.raises(EgmError, match="set_target"):
        make_link("pose").set_correction([0, 0, 0])


# --------------------------------------------------------------------------- pose guidance

def test_pose_mode_guards_every_target():
    clock = Clock()
    refuse_y = lambda p, q: (abs(p[1]) < 50.0, "torch would hit the main pipe")  # noqa: E731
    link = make_link("pose", gate=refuse_y, clock=clock)
    ctl = Controller(link, clock)
    p, q = pose_of(ctl.cycle())  # no measurement: the robot's own pose
    np.testing.assert_allclose(p, FB_POS)
    np.testing.assert_allclose(q, FB_QUAT)
    assert link.set_target(FB_POS + [1.5, 0, 0], FB_QUAT).ok
    p, _ = pose_of(ctl.cycle())
    np.testing.assert_allclose(p, FB_POS + [1.5, 0, 0])
    assert link.stats.commands == 1

    def refused(reason, pos, quat=FB_QUAT, static=True):
        v = link.set_target(pos, quat)
        if static:
            assert not v.ok and v.reason == reason
        else:
            assert v.ok  # passes when given; refused when the reply is built
        last = pose_of(ctl.cycle())  # the last sent target again, never the refused one
        np.testing.assert_allclose(last[0], FB_POS + [1.5, 0, 0])
        assert link.stats.refused[reason] == 1

    refused("step_too_large", FB_POS + [4.0, 0, 0], static=False)
    half = math.radians(link.config.safety.max_step_deg + 1.0) / 2  # 1 deg past the limit
    turned = np.array([0.0, math.sin(half), math.cos(half), 0.0])
    refused("rotation_step_too_large", FB_POS + [1.5, 0, 0], turned, static=False)
    refused("bad_quaternion", FB_POS + [1.5, 0, 0], FB_QUAT * 0.9)
    refused("non_finite", FB_POS + [1.5, math.nan, 0])
    refused("gate", FB_POS + [1.5, 60.0, 0])
    # walking 1.5 mm a cycle is within max_step_mm, but the robot does not follow (its
    # feedback stays put): past max_lead_mm (30 mm) the target is refused
    for k in range(2, 30):
        link.set_target(FB_POS + [1.5 * k, 0, 0], FB_QUAT)
        p, _ = pose_of(ctl.cycle())
        assert np.linalg.norm(p - FB_POS) <= 30.0
    assert link.stats.refused["too_far_from_robot"] == 1


def test_pose_watchdog_holds_the_last_accepted_pose():
    """Issue 25: a hold commands the last accepted pose, never the pose the datagram being
    answered reports (that pose comes from the wire, where anyone can forge or replay it). The
    robot finishes the last vetted step and stops there (it used to stop "where it is", at the
    fed-back pose: a forged EgmRobot could move it 50 mm)."""
    clock = Clock()
    link = make_link("pose", clock=clock)
    ctl = Controller(link, clock)
    link.set_target(FB_POS + [1.0, 0, 0], FB_QUAT)
    ctl.cycle()
    moving = FB_POS + [0.4, 0.0, 0.0]
    for _ in range(60):  # 240 ms: past the watchdog
        p, q = pose_of(ctl.cycle(pos=moving))
    np.testing.assert_allclose(p, FB_POS + [1.0, 0, 0])  # the last sent target
    np.testing.assert_allclose(q, FB_QUAT)
    assert link.holding and link.stats.watchdog_trips == 1


# --------------------------------------------------------------------------- datagrams

def _sensor_bytes() -> bytes:
    s = EgmSensor()
    s.header.mtype = EgmHeader.MSGTYPE_CORRECTION
    c = s.planned.cartesian
    c.pos.x, c.pos.y, c.pos.z = 1.0, 2.0, 3.0
    c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = 1.0, 0.0, 0.0, 0.0
    return s.SerializeToString()


def _no_header() -> bytes:
    r = EgmRobot.FromString(robot_bytes(1))
    r.ClearField("header")
    return r.SerializeToString()


@pytest.mark.parametrize("reason, data, sender", [
    ("foreign_sender", robot_bytes(1), ("127.0.0.2", 6511)),
    ("foreign_sender", robot_bytes(1), ("127.0.0.1", 40000)),
    ("foreign_sender", robot_bytes(1), ("not an address", 6511)),
    ("empty", b"", CTRL),
    ("oversized", robot_bytes(1) + b"\x7a\x90\x08" + b"\0" * 1040, CTRL),
    ("unparseable", b"\xff\xff\xff\xff", CTRL),
    ("unparseable", robot_bytes(1)[:-3], CTRL),
    ("wrong_type", _sensor_bytes(), CTRL),
    ("wrong_type", robot_bytes(1, mtype=EgmHeader.MSGTYPE_CORRECTION), CTRL),
    ("wrong_type", _no_header(), CTRL),
    ("non_finite", robot_bytes(1, pos=[math.nan, 0.0, 0.0]), CTRL),
    ("non_finite", robot_bytes(1, joints=[0.0, math.inf, 0, 0, 0, 0]), CTRL),
])
def test_bad_datagrams_are_counted_and_dropped(reason, data, sender):
    link = make_link()
    assert link.handle_datagram(data, sender) is None
    assert link.stats.dropped == {reason: 1} and link.stats.received == 0


def test_pose_mode_needs_the_fed_back_pose():
    r = EgmRobot.FromString(robot_bytes(1))
    r.feedBack.ClearField("cartesian")
    link = make_link("pose")
    assert link.handle_datagram(r.SerializeToString(), CTRL) is None
    assert link.stats.dropped == {"no_feedback_pose": 1}
    assert make_link("pathcorr").handle_datagram(r.SerializeToString(), CTRL) is not None


def test_sequence_numbers_drop_duplicates_and_reordered_only():
    link = make_link()
    answer = lambda seq: link.handle_datagram(robot_bytes(seq), CTRL)  # noqa: E731
    assert answer(10) is not None
    assert answer(10) is None                       # duplicate
    assert answer(13) is not None                   # 11 and 12 lost
    assert answer(12) is None                       # came late: reordered
    stats = link.stats
    assert stats.dropped == {"duplicate": 1, "out_of_order": 1}
    assert stats.robot_missing == 2 and stats.received == 2
    # seqno wraps around at 2^32
    link2 = make_link()
    assert link2.handle_datagram(robot_bytes(0xFFFFFFFF), CTRL) is not None
    assert link2.handle_datagram(robot_bytes(0), CTRL) is not None
    assert link2.stats.robot_missing == 0
    # one datagram far from the newest is never a new session (issue 25: a replay more than
    # reorder_window behind used to restart the session and be answered; tests/
    # test_egm_attacks.py has what a restart takes)
    assert link2.handle_datagram(robot_bytes(5000), CTRL) is None  # far ahead, no time ran
    assert link2.handle_datagram(robot_bytes(0xFFFFFF00), CTRL) is None  # behind, old clock
    assert link2.handle_datagram(robot_bytes(1), CTRL) is not None  # the stream goes on
    assert link2.stats.dropped == {"unconfirmed_jump": 1, "replayed": 1}


def test_fields_of_newer_controllers_are_accepted():
    # RobotWare 7 adds e.g. moveIndex (11) and RAPIDfromRobot (13): unknown here, not an error
    extra = b"\x58\x07" + b"\x6a\x02\x08\x01"
    link = make_link()
    assert link.handle_datagram(robot_bytes(1) + extra, CTRL) is not None


def test_controller_silence_holds_one_cycle_then_guides():
    clock = Clock()
    link = make_link(clock=clock, max_age_ms=1000.0, watchdog_ms=200.0)
    ctl = Controller(link, clock)
    link.set_correction([0.0, 0.5, 0.0])
    ctl.cycle()
    clock.t += 0.300  # the controller says nothing for 300 ms; the tracker keeps measuring
    link.set_correction([0.0, 0.6, 0.0])
    first = ctl.cycle()
    assert link.stats.controller_silences == 1
    assert offset(first) == [0.0, 0.5, 0.0] and first.pathCorr.age == 0
    assert link.stats.holds == {"controller_silence": 1}
    assert offset(ctl.cycle()) == pytest.approx([0.0, 0.6, 0.0])


# --------------------------------------------------------------------------- fuzzing

def _datagram(kind: int, seed: int, raw: bytes) -> bytes:
    """A fuzz input of one of 5 kinds, from a seed: 0 random bytes; 1 an ``EgmRobot`` with
    seqno ``seed`` and a random pose, now and then flipped or cut; 2 the same with a seqno 1-3
    below ``seed`` (a duplicate or a reordered one after kind 1 of ``seed - 1``); 3 an
    ``EgmSensor`` and 4 nothing, both flipped, cut and given a tail.

    Hypothesis draws only small values; the bulk comes from a seeded RNG, which keeps thousands
    of examples fast (drawing every byte through hypothesis costs milliseconds each)."""
    rng = random.Random(seed)
    if kind == 0:
        return raw + rng.randbytes(rng.randrange(0, 1200))
    if kind in (1, 2):
        seq = seed if kind == 1 else seed - 1 - rng.randrange(3)
        pos = [rng.uniform(-2000.0, 2000.0) for _ in range(3)]
        buf = bytearray(robot_bytes(seq & 0xFFFFFFFF, pos, FB_QUAT))
        if rng.random() < 0.3:
            buf[rng.randrange(len(buf))] ^= rng.randrange(1, 256)
        if rng.random() < 0.3:
            buf = buf[:rng.randrange(len(buf))]
        return bytes(buf)
    buf = bytearray(_sensor_bytes() if kind == 3 else b"")
    for _ in range(rng.randrange(0, 6) if buf else 0):
        buf[rng.randrange(len(buf))] ^= rng.randrange(1, 256)
    return bytes(buf[:rng.randrange(0, len(buf) + 1)]) + raw


# 1000 hypothesis examples x one datagram of each of the 5 kinds = 5000 inputs: hypothesis'
# own bookkeeping costs ~1-3 ms an example, the link ~0.05 ms a datagram
FUZZ = settings(max_examples=1000, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
_FUZZ_LINK = make_link(latency_samples=1)  # its clock stands still: the one measurement never ages
_FUZZ_LINK.set_correction([0.0, 0.5, 0.0])


@FUZZ
@given(seed=st.integers(0, 2**32 - 1), raw=st.binary(max_size=16))
def test_fuzz_datagram_parsers_never_crash_and_answer_only_safely(seed, raw):
    link = _FUZZ_LINK
    for kind in range(5):
        data = _datagram(kind, seed + kind, raw)
        dropped = sum(link._stats.dropped.values())
        out = link.handle_datagram(data, CTRL)
        if out is None:  # dropped, and counted
            assert sum(link._stats.dropped.values()) == dropped + 1
        else:
            msg, why = parse_sensor(out, "pathcorr")
            assert msg is not None, why
            assert offset(msg) == [0.0, 0.5, 0.0]  # the only correction ever accepted
            robot, _ = parse_robot(data)
            assert robot is not None and all(map(math.isfinite, robot.feedBack.joints.joints))
        for mode in ("pose", "pathcorr"):  # the controller side's parser too
            msg, why = parse_sensor(data, mode)
            assert (msg is None) != (why == "")


def test_fuzz_inputs_reach_every_outcome():
    """The fuzz generator is worth its examples: it reaches replies and every drop reason.

    The link's clock runs 8 ms a datagram, 40 ms a seed: the controller's seqno steps by 10 a
    seed, and since issue 25 a jump ahead is taken only as far as the link's own clock explains
    it (one 4 ms period a seqno; a frozen clock took jumps of 10 at once, as it took the forged
    one of 60 that then blocked the genuine stream)."""
    clock = Clock()
    link = make_link(latency_samples=1, clock=clock, max_age_ms=1e9, watchdog_ms=1e9)
    link.set_correction([0.0, 0.5, 0.0])
    for seed in range(0, 2000, 10):
        for kind in range(5):
            clock.t += 0.008
            link.handle_datagram(_datagram(kind, seed + kind, b""), CTRL)
    stats = link.stats
    assert stats.sent > 10
    assert {"unparseable", "wrong_type", "duplicate", "out_of_order", "oversized",
            "empty"} <= set(stats.dropped), stats.dropped


@settings(max_examples=300, derandomize=True, database=None, deadline=None)
@given(values=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=7,
                       max_size=7), seq=st.integers(0, 2**32 - 1))
def test_fuzz_robot_values(values, seq):
    data = robot_bytes(seq, values[:3], values[3:])
    robot, why = parse_robot(data)
    finite = all(map(math.isfinite, values))
    assert (robot is not None) == finite and (why == "non_finite") == (not finite)


# --------------------------------------------------------------------------- on the wire

@pytest.fixture(scope="module")
def robot_model():
    from torchseam.robot.kinematics import load_irb1410

    return load_irb1410()


CELL_TOOL = load_cell().tool.matrix()  # the simulated controller's tool: the cell's torch


def _ephemeral(cfg, mode, controller_port):
    return dataclasses.replace(cfg, mode=mode, network=dataclasses.replace(
        cfg.network, port=0, controller_port=controller_port))


# A canary per CPU in a process of its own: it sleeps 1 ms at a time at real-time priority and
# prints each wake-up that came more than 1 ms late, as (start, end) wall-clock ns. A reply is
# late when ~3.5 of its 4 ms went missing; that cannot happen without a stall of >= 1 ms somewhere
# (the sensor, or the controller sending late), which a real-time thread on the same CPU sees.
_CANARY = r"""
import os, sys, threading, time
stalls, stop = [], threading.Event()
def run(cpu):
    try:
        os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(20))
    except (AttributeError, OSError):
        pass
    while not stop.is_set():
        t0 = time.time_ns()
        time.sleep(0.001)
        t1 = time.time_ns()
        if t1 - t0 > 2_000_000:  # woke more than 1 ms late
            stalls.append((t0 + 1_000_000, t1))
threads = [threading.Thread(target=run, args=(c,)) for c in sorted(os.sched_getaffinity(0))]
for t in threads: t.start()
print("ready", flush=True)
sys.stdin.read()
stop.set()
for t in threads: t.join()
print(" ".join(f"{a}:{b}" for a, b in stalls), flush=True)
"""


class StallMonitor:
    """Records when the machine itself stalls (a neighbour or the hypervisor takes the CPU):
    no program on it, at any priority, can answer in time then."""

    def __enter__(self) -> StallMonitor:
        self.proc = subprocess.Popen([sys.executable, "-c", _CANARY], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout.readline().strip() == "ready"
        return self

    def __exit__(self, *exc) -> None:
        out, _ = self.proc.communicate("", timeout=30)
        self.stalls = [tuple(map(int, w.split(":"))) for w in out.split()]

    @staticmethod
    def wait_for_quiet(max_wait_s: float = 60.0, probe_s: float = 1.0,
                       max_stalls: int = 2) -> tuple[float, int]:
        """Wait (at most ``max_wait_s``) for a ``probe_s`` second in which the canary records
        at most ``max_stalls`` stalls; returns (seconds waited, stalls in the last probe).
        A shared VM's stalls come in storms (here: 17 to 17778 per 10 s within minutes): a
        cell would not start a weld on a PC in one either. After the wait the session runs
        whatever the machine does, and its stalls are recorded as before."""
        t0, n = time.monotonic(), 0
        while True:
            with StallMonitor() as probe:
                time.sleep(probe_s)
            n = len(probe.stalls)
            waited = time.monotonic() - t0
            if n <= max_stalls or waited >= max_wait_s:
                return waited, n

    def explains(self, sent_ns: int, period_ns: int = 4_000_000) -> bool:
        """Did a stall come within 5 ms of the reply window [sent, sent + one period]? On a
        machine that stalls, smaller delays the canary cannot see cluster around the big ones."""
        lo, hi = sent_ns - 5_000_000, sent_ns + period_ns + 5_000_000
        return any(a < hi and b > lo for a, b in self.stalls)


def _link_within_budget(link, sent_ns: int, cfg) -> bool:
    """Did the link answer the EgmRobot sent at ``sent_ns`` (or the newer one that superseded
    it) with at most ``link.late_reply_ms`` of its own CPU time? The reply is the first logged
    one whose newest EgmRobot arrived after ``sent_ns``; its batch must begin within a period
    (the next EgmRobot never leaves sooner), else the log holds no record of this one."""
    period_ns = 1e9 / cfg.sim_controller.rate_hz
    rec = min((r for r in link.late_log if r.rx_ns >= sent_ns), key=lambda r: r.rx_ns,
              default=None)
    return (rec is not None and rec.first_rx_ns < sent_ns + period_ns
            and rec.cpu_ms <= cfg.link.late_reply_ms)


def test_loopback_session_250hz_10s_without_late_replies(robot_model, record_property):
    """10 s at 250 Hz: the sensor (link + synthetic tracker) in its own process, as in a cell.

    Both sides ask for SCHED_FIFO priority 10, as a cell PC that shares its cores should run
    the link: on this 2-core VM with neighbours keeping ~4.5 tasks runnable, normal scheduling
    left 103 of 2500 replies late, real-time none. Refused (no CAP_SYS_NICE), the session runs
    at normal priority, which keeps up on an idle machine; the printed table says which. A VM's
    hypervisor can still take a CPU away for tens of ms (measured here: a real-time canary
    sleeping 1 ms woke up to 36 ms late, 10 times in 10 s; at worst 196 stalls in 10 s, and on
    a CI machine 913): a canary process records such stalls, and a late reply must line up
    with one, or the link's own record of it (``EgmStats.late_log``) must show that the link
    did its work within ``link.late_reply_ms`` of CPU time while the rest went to waiting for
    a CPU. On a quiet machine: no late reply at all.
    """
    cfg = load_egm_config()
    cfg = dataclasses.replace(
        cfg, link=dataclasses.replace(cfg.link, rt_priority=10),
        sim_controller=dataclasses.replace(cfg.sim_controller, rt_priority=10))
    waited, probe_stalls = StallMonitor.wait_for_quiet()
    with StallMonitor() as machine:
        result = loopback_session(cfg, 10.0, robot=robot_model, tool=CELL_TOOL, mode="pathcorr")
    sim, link = result.sim, result.link
    print(f"\n  waited {waited:.1f} s for a quiet second ({probe_stalls} stalls in the last)")
    stalled = [t for t in sim.late_cycles_ns if machine.explains(t)]
    # the link's own record of each late reply: within its CPU budget, the time that made it
    # late was the machine's (the link thread waiting for a CPU, or taken off one)
    off_cpu = [t for t in sim.late_cycles_ns
               if t not in stalled and _link_within_budget(link, t, cfg)]
    explained = stalled + off_cpu
    worst = max((b - a for a, b in machine.stalls), default=0) / 1e6
    print(f"\n{result.table()}\n  machine stalls > 1 ms: {len(machine.stalls)} "
          f"(longest {worst:.1f} ms); late replies during one: {len(stalled)}; others with "
          f"the link's work within its budget, the machine holding its thread: {len(off_cpu)}")
    ctl, sen = latency_summary(sim.latency_ms), link.latency_summary()
    for name, d in (("controller", ctl), ("sensor", sen)):
        record_property(f"reply_latency_{name}_p50_ms", round(d["p50"], 3))
        record_property(f"reply_latency_{name}_p99_ms", round(d["p99"], 3))
    assert cfg.sim_controller.rate_hz == 250.0
    assert sim.cycles == 2500 and sim.sent == 2500 and sim.expected == 2500
    assert len(sim.late_cycles_ns) == sim.late_replies
    # a machine stalling more than twice a second is itself unfit for a 4 ms loop; there, delays
    # below the canary's threshold add up as well: allow 1 unexplained late reply per 1000
    busy = len(machine.stalls) > 20
    allowed = sim.cycles // 1000 if busy else 0
    assert sim.late_replies - len(explained) <= allowed, (
        f"{sim.late_replies - len(explained)} late replies while the machine ran normally "
        f"({len(machine.stalls)} machine stalls, {allowed} allowed)\n" + result.table())
    # every EgmRobot answered; during a stall the sensor answers only the newest of those that
    # queued up (superseded), and each one it skipped is a late reply
    assert link.received == 2500 and link.sent + link.superseded == 2500
    assert link.superseded <= sim.late_replies
    assert 0 <= link.sent - sim.replies <= 1 and not sim.rejected  # the very last in flight
    assert not link.dropped and not link.refused
    assert link.commands >= 2400  # the first cycles may hold until the first measurement
    assert ctl["p50"] < 2.0


def test_pose_session_moves_the_robot_to_the_target(robot_model):
    from torchseam.core.transforms import matrix_to_quat as matrix_quat
    from torchseam.robot.sim_controller import SimController

    cfg = load_egm_config()
    sim = SimController(cfg, mode="pose", robot=robot_model, tool=CELL_TOOL,
                        bind_address=("127.0.0.1", 0))
    try:
        with EgmLink(_ephemeral(cfg, "pose", sim.address[1])) as link:
            sim.sensor_address = link.address
            start = sim.tcp_pose()
            q0 = matrix_quat(start[:3, :3])
            sim.start()
            target = start[:3, 3].copy()
            for _ in range(10):  # walk 10 mm sideways in 1 mm steps
                target += [0.0, 1.0, 0.0]
                assert link.set_target(target, q0).ok
                time.sleep(0.02)
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline:
                link.set_target(target, q0)  # keep the measurement fresh
                if np.linalg.norm(sim.tcp_pose()[:3, 3] - target) < 0.05:
                    break
                time.sleep(0.02)
            np.testing.assert_allclose(sim.tcp_pose()[:3, 3], target, atol=0.05)
            np.testing.assert_allclose(sim.tcp_pose()[:3, :3], start[:3, :3], atol=1e-4)
            assert not link.stats.refused and not link.stats.dropped
    finally:
        sim.stop()


def test_fault_injection_on_the_wire(robot_model, caplog):
    from torchseam.robot.sim_controller import Fault, SimController

    cfg = load_egm_config()
    sim = SimController(cfg, mode="pathcorr", robot=robot_model, tool=CELL_TOOL,
                        bind_address=("127.0.0.1", 0))
    stop_feed = threading.Event()
    link = EgmLink(_ephemeral(cfg, "pathcorr", sim.address[1]))
    sim.sensor_address = link.address
    feeder = threading.Thread(target=run_feed, args=(link, Feed(), 60.0, None, stop_feed.is_set),
                              daemon=True)
    foreign = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    foreign.bind(("127.0.0.1", 0))
    try:
        link.start()
        feeder.start()
        sim.start()
        sim.wait_cycles(25)

        def run_phase(fault: Fault, n: int):
            c0, before = sim.cycles, link.stats
            sim.inject(fault, n)
            sim.wait_cycles(c0 + n + 15)
            return before, link.stats

        def delta(before, after, name: str, key: str | None = None) -> int:
            b, a = getattr(before, name), getattr(after, name)
            return a[key] - b[key] if key is not None else a - b

        b, a = run_phase(Fault.DROP, 5)
        assert delta(b, a, "robot_missing") == 5 and a.dropped == b.dropped
        b, a = run_phase(Fault.DUPLICATE, 5)
        assert delta(b, a, "dropped", "duplicate") == 5 and delta(b, a, "robot_missing") == 0
        b, a = run_phase(Fault.REORDER, 3)  # held back, then sent after the next (newer) one
        assert delta(b, a, "dropped", "out_of_order") == 3
        assert delta(b, a, "robot_missing") == 3
        for fault, reason in ((Fault.CORRUPT, "unparseable"), (Fault.OVERSIZED, "oversized")):
            b, a = run_phase(fault, 5)
            assert delta(b, a, "dropped", reason) == 5, a.dropped
            assert delta(b, a, "robot_missing") == 5
        # a valid EgmRobot from a foreign port: dropped, and never answered
        b = link.stats
        foreign.sendto(robot_bytes(10**6), link.address)
        foreign.settimeout(0.2)
        with pytest.raises(TimeoutError):
            foreign.recvfrom(2048)
        assert delta(b, link.stats, "dropped", "foreign_sender") == 1
        # controller silence (300 ms > watchdog 200 ms): flagged, then one holding reply
        with caplog.at_level(logging.WARNING, logger="torchseam.robot.egm"):
            b, a = run_phase(Fault.SILENCE, 75)
        assert delta(b, a, "controller_silences") == 1
        assert delta(b, a, "holds", "controller_silence") == 1
        assert any("controller silent" in r.getMessage() for r in caplog.records)
        # the tracker goes quiet: first stale, then the watchdog; the last offset holds
        # (age 0, no jump back onto the path) until measurements come back
        stop_feed.set()
        feeder.join()
        t_stop = time.monotonic()
        sim.wait_cycles(sim.cycles + 100)  # 400 ms
        assert link.holding and link.stats.watchdog_trips == 1
        held = [m for t, m in sim.replies() if t > t_stop + 0.25]
        assert held and all(m.pathCorr.age == 0 for m in held)
        assert len({tuple(offset(m)) for m in held}) == 1
        link.set_correction(offset(held[-1]))
        sim.wait_cycles(sim.cycles + 10)
        assert not link.holding
        # through all of it: every valid EgmRobot answered (or skipped for a newer one),
        # every reply arrived, nothing but the stale measurement refused
        sim.stop()
        time.sleep(0.05)
        k, s = link.stats, sim.stats
        assert k.sent + k.superseded == k.received
        assert 0 <= k.sent - s.replies <= 1 and not s.rejected  # one may be in flight
        assert set(k.refused) <= {"stale"}
        assert sum(s.faults.values()) == 5 + 5 + 3 + 5 + 5 + 75
    finally:
        stop_feed.set()
        sim.stop()
        link.stop()
        foreign.close()


class _HeldSend:
    """The controller's socket, its thread held ``hold_s`` inside the ``at``-th sendto before
    the datagram leaves (as the GIL, the scheduler or a hypervisor can hold it)."""

    def __init__(self, sock: socket.socket, at: int, hold_s: float) -> None:
        self.sock, self.at, self.hold_s, self.n = sock, at, hold_s, 0
        self.window_ns: tuple[int, int] | None = None  # [before the hold, after the send]
        self.next_sent_ns: int | None = None  # right before the datagram after it

    def sendto(self, data: bytes, address) -> int:
        self.n += 1
        if self.n == self.at + 1:
            self.next_sent_ns = time.time_ns()
        if self.n != self.at:
            return self.sock.sendto(data, address)
        t0 = time.time_ns()
        time.sleep(self.hold_s)
        out = self.sock.sendto(data, address)
        self.window_ns = (t0, time.time_ns())
        return out

    def __getattr__(self, name: str):
        return getattr(self.sock, name)


def test_a_controller_held_on_its_way_out_is_not_a_late_reply(robot_model):
    """The simulated controller judges a reply from when its EgmRobot left the socket (kernel
    transmit stamp), not from when it began to send: held 8 ms (two periods) before the
    datagram left, the sensor's prompt reply is on time, and the next EgmRobot still leaves a
    full period after it. Stamped before the hold, that cycle was late and its reply, heard
    after the next EgmRobot had already left, counted as an extra one (CI, 10 s session)."""
    from torchseam.robot.sim_controller import SimController

    cfg = load_egm_config()
    sim = SimController(cfg, mode="pathcorr", robot=robot_model, tool=CELL_TOOL,
                        bind_address=("127.0.0.1", 0))
    held = sim._sock = _HeldSend(sim._sock, at=150, hold_s=0.008)
    stop_feed = threading.Event()
    link = EgmLink(_ephemeral(cfg, "pathcorr", sim.address[1]))
    sim.sensor_address = link.address
    feeder = threading.Thread(target=run_feed, args=(link, Feed(), 60.0, None, stop_feed.is_set),
                              daemon=True)
    try:
        link.start()
        feeder.start()
        sim.start()
        sim.wait_cycles(200)
    finally:
        stop_feed.set()
        sim.stop()
        link.stop()
    assert held.window_ns is not None, "the held send never happened"
    t0, t1 = held.window_ns
    s = sim.stats
    if s.unstamped == s.expected:  # what the test is about needs them
        pytest.skip("this kernel gives no transmit time stamps on loopback")
    assert s.unstamped == 0
    late_there = [t for t in s.late_cycles_ns if t0 - 1_000_000 <= t <= t1 + 1_000_000]
    assert not late_there, f"the held cycle counted as late ({len(late_there)})"
    # (extra replies are not counted here: any machine stall in the run can make one)
    # the sensor's window: the next EgmRobot left at least a period after the held one, which
    # left after the hold (0.1 ms for clock readings)
    period_ns = 1e9 / cfg.sim_controller.rate_hz
    assert held.next_sent_ns - t0 >= held.hold_s * 1e9 + period_ns - 100_000
    # the hold shows where it was: in the controller's own send time
    assert max(s.send_ms) >= 8.0


def test_late_log_tells_waiting_from_working():
    """A reply late because the EgmRobot waited for the serving thread shows as waiting; one
    late because the link worked on it shows as CPU time (``EgmStats.late_log``)."""
    cfg = load_egm_config()
    ctrl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctrl.bind(("127.0.0.1", 0))
    ctrl.settimeout(2.0)
    link = EgmLink(_ephemeral(cfg, "pathcorr", ctrl.getsockname()[1]))
    late_ms = cfg.link.late_reply_ms
    try:
        # 1. nobody serves for 3 x late_reply_ms: the datagram waits in the kernel
        ctrl.sendto(robot_bytes(1), link.address)
        time.sleep(3 * late_ms / 1e3)
        assert link.serve_once(1.0) == 1
        ctrl.recvfrom(2048)
        (r,) = link.stats.late_log
        assert r.first_rx_ns == r.rx_ns and r.wait_ms >= 2.5 * late_ms
        assert r.cpu_ms < r.wait_ms / 2 and link.stats.late_replies == 1
        # 2. the link itself works for 3 x late_reply_ms on the answer
        answer = link._answer

        def slow(robot):
            t_end = time.thread_time() + 3 * late_ms / 1e3
            while time.thread_time() < t_end:
                pass
            return answer(robot)

        link._answer = slow
        ctrl.sendto(robot_bytes(2), link.address)
        assert link.serve_once(1.0) == 1
        ctrl.recvfrom(2048)
        r = link.stats.late_log[-1]
        assert r.cpu_ms >= 2.5 * late_ms and r.work_ms >= r.cpu_ms - 0.05  # clocks read in turn
        assert link.stats.late_replies == 2
    finally:
        link.stop()
        ctrl.close()
