"""The EGM safety policy as pure functions (torchseam.robot.egm.policy): each decision called with
plain values (poses, limits, time stamps), no link, no socket, no clock."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from torchseam.robot.egm.config import load_egm_config
from torchseam.robot.egm.policy import (
    ACCEPT,
    ACCEPTED,
    DROP,
    HOLD_NEW_SESSION,
    HOLD_NO_MEASUREMENT,
    HOLD_SILENCE,
    HOLD_WATCHDOG,
    NEW_SESSION,
    SequenceTracker,
    Verdict,
    check_age,
    check_correction_step,
    check_gate,
    check_measurement,
    check_pose_step,
    controller_port,
    controller_silent,
    correction_command,
    hold_cause,
    hold_pose,
    pose_command,
    reply_age_ms,
    within_step,
)

SAFETY = dataclasses.replace(load_egm_config().safety, max_step_mm=2.0, max_step_deg=1.0,
                             max_lead_mm=10.0, max_correction_mm=5.0, max_age_ms=100.0,
                             watchdog_ms=50.0)
P0 = np.array([984.0, 0.0, 624.0])
Q0 = np.array([0.0, 0.0, 1.0, 0.0])


def turned(q: np.ndarray, deg: float) -> np.ndarray:
    """``q`` turned by ``deg`` about the base z axis (w, x, y, z)."""
    h = math.radians(deg) / 2
    w, x, y, z = math.cos(h), 0.0, 0.0, math.sin(h)
    a = q
    return np.array([w * a[0] - x * a[1] - y * a[2] - z * a[3],
                     w * a[1] + x * a[0] + y * a[3] - z * a[2],
                     w * a[2] - x * a[3] + y * a[0] + z * a[1],
                     w * a[3] + x * a[2] - y * a[1] + z * a[0]])


# --------------------------------------------------------------------------- measurements

@pytest.mark.parametrize("vec, quat", [
    (np.array([math.nan, 0.0, 0.0]), Q0),
    (P0, np.array([math.inf, 0.0, 0.0, 0.0])),
    (np.array([0.0, -math.inf, 0.0]), None),
])
def test_a_non_finite_target_is_refused(vec, quat):
    mode = "pathcorr" if quat is None else "pose"
    v = check_measurement(vec, quat, 10.0, 10.0, SAFETY, mode)
    assert (v.ok, v.reason) == (False, "non_finite")
    assert check_measurement(P0, Q0, math.nan, 10.0, SAFETY, "pose").reason == "non_finite"


def test_measurement_shape_quaternion_and_correction_size():
    assert check_measurement(P0, Q0, 10.0, 10.0, SAFETY, "pose") is ACCEPTED
    assert check_measurement(P0[:2], Q0, 10.0, 10.0, SAFETY, "pose").reason == "bad_shape"
    assert check_measurement(P0, Q0[:3], 10.0, 10.0, SAFETY, "pose").reason == "bad_shape"
    assert check_measurement(P0, 1.01 * Q0, 10.0, 10.0, SAFETY, "pose").reason == \
        "bad_quaternion"
    assert check_measurement(P0, 1.0005 * Q0, 10.0, 10.0, SAFETY, "pose").ok  # within QUAT_TOL
    big = np.array([0.0, 5.01, 0.0])
    assert check_measurement(big, None, 10.0, 10.0, SAFETY, "pathcorr").reason == \
        "correction_too_large"
    assert check_measurement(big * 0.99, None, 10.0, 10.0, SAFETY, "pathcorr").ok
    # the correction limit is pathcorr's: a pose-mode gate pose is a position, not an offset
    assert check_measurement(P0, Q0, 10.0, 10.0, SAFETY, "pathcorr").ok


def test_age_limits():
    assert check_age(10.0, 10.0999, 100.0).ok
    v = check_age(10.0, 10.1001, 100.0)
    assert (v.ok, v.reason) == (False, "stale") and "max_age_ms" in v.detail
    assert check_age(10.0005, 10.0, 100.0).ok                    # under a ms ahead: rounding
    assert check_age(10.002, 10.0, 100.0).reason == "future_timestamp"
    assert check_measurement(P0, Q0, 9.0, 10.0, SAFETY, "pose").reason == "stale"


def test_the_gate_refuses_and_a_failing_gate_never_opens():
    seen = []

    def gate(p, q):
        seen.append((p, q))
        p[0] = -1.0  # a gate that scribbles on its input must not change the caller's pose
        return p[2] > 0, "below the table"

    p = P0.copy()
    assert check_gate(None, p, Q0) is ACCEPTED
    assert check_gate(gate, p, Q0).ok and p[0] == 984.0
    v = check_gate(gate, np.array([0.0, 0.0, -5.0]), Q0)
    assert v == Verdict(False, "gate", "unreachable: below the table")

    def broken(p, q):
        raise RuntimeError("IK blew up")

    v = check_gate(broken, P0, Q0)
    assert (v.ok, v.reason) == (False, "gate_error") and "IK blew up" in v.detail


# --------------------------------------------------------------------------- steps

def test_a_pose_step_over_the_limit_is_refused():
    ref = (P0, Q0)
    ok = check_pose_step((P0 + [0.0, 1.99, 0.0], Q0), ref, P0, SAFETY)
    assert ok is ACCEPTED
    v = check_pose_step((P0 + [0.0, 2.01, 0.0], Q0), ref, P0, SAFETY)
    assert (v.ok, v.reason) == (False, "step_too_large") and "max_step_mm 2.0" in v.detail
    v = check_pose_step((P0, turned(Q0, 1.5)), ref, P0, SAFETY)
    assert (v.ok, v.reason) == (False, "rotation_step_too_large")
    assert check_pose_step((P0, turned(Q0, 0.5)), ref, P0, SAFETY).ok
    # within a step of the last reply, but too far ahead of where the robot really is
    v = check_pose_step((P0 + [0.0, 1.0, 0.0], Q0), ref, P0 - [0.0, 9.5, 0.0], SAFETY)
    assert (v.ok, v.reason) == (False, "too_far_from_robot")


def test_a_correction_step_is_measured_from_the_last_offset_or_zero():
    assert check_correction_step(np.array([0.0, 1.9, 0.0]), None, SAFETY).ok
    v = check_correction_step(np.array([0.0, 2.1, 0.0]), None, SAFETY)
    assert (v.ok, v.reason) == (False, "step_too_large")
    assert check_correction_step(np.array([0.0, 2.1, 0.0]), np.array([0.0, 1.0, 0.0]),
                                 SAFETY).ok


def test_within_step_is_the_last_check_before_the_wire():
    assert within_step(None, None, P0 + 100.0, Q0, SAFETY)  # nothing sent yet in the session
    assert within_step(P0, Q0, P0 + [2.0, 0.0, 0.0], Q0, SAFETY)        # on the limit
    assert not within_step(P0, Q0, P0 + [2.01, 0.0, 0.0], Q0, SAFETY)
    assert not within_step(P0, Q0, P0, turned(Q0, 1.1), SAFETY)
    assert within_step(P0, None, P0 + [0.0, 0.0, 1.0], None, SAFETY)  # pathcorr: no turn


# --------------------------------------------------------------------------- holds

def test_a_hold_commands_the_last_accepted_pose():
    last = (P0 + [0.0, 1.0, 0.0], Q0)
    start = (P0, Q0)
    assert hold_pose(last, start) is last
    assert hold_pose(None, start) is start  # nothing sent yet: the session's start pose
    with pytest.raises(ValueError):
        hold_pose(None, None)
    # a hold (no target) commands the last reply, never anything new
    assert pose_command(None, last, start, SAFETY) is last
    # a target within a step of the last reply is commanded...
    target = (P0 + [0.0, 2.5, 0.0], Q0)
    assert pose_command(target, last, start, SAFETY) is target
    # ...one that would jump is replaced by the hold
    far = (P0 + [0.0, 4.0, 0.0], Q0)
    assert pose_command(far, last, start, SAFETY) is last
    # before the first reply of a session there is no step to keep: the target goes
    assert pose_command(far, None, start, SAFETY) is far


def test_a_pathcorr_hold_repeats_the_last_offset_with_age_zero():
    last = np.array([0.0, 1.0, 0.0])
    offset, age = correction_command(None, 0.0, 10.0, last, SAFETY)
    assert offset is last and age == 0
    offset, age = correction_command(None, 0.0, 10.0, None, SAFETY)
    np.testing.assert_array_equal(offset, np.zeros(3))
    assert age == 0
    new = np.array([0.0, 2.5, 0.0])
    offset, age = correction_command(new, 9.98, 10.0, last, SAFETY)
    assert offset is new and age == 20
    offset, age = correction_command(np.array([0.0, 4.0, 0.0]), 9.98, 10.0, last, SAFETY)
    assert offset is last and age == 0
    assert reply_age_ms(10.5, 10.0) == 0          # never negative
    assert reply_age_ms(0.0, 1e9) == 0xFFFFFFFF   # fits the uint32 field


def test_hold_causes_in_order():
    kw = dict(arrived_at=9.99, now=10.0, watchdog_ms=50.0)
    assert hold_cause(new_session=False, resync=False, **kw) == ""
    assert hold_cause(new_session=True, resync=True, **kw) == HOLD_NEW_SESSION
    assert hold_cause(new_session=False, resync=True, **kw) == HOLD_SILENCE
    assert hold_cause(new_session=False, resync=False, arrived_at=None, now=10.0,
                      watchdog_ms=50.0) == HOLD_NO_MEASUREMENT
    assert hold_cause(new_session=False, resync=False, arrived_at=10.0 - 0.0501, now=10.0,
                      watchdog_ms=50.0) == HOLD_WATCHDOG
    assert hold_cause(new_session=False, resync=False, arrived_at=10.0 - 0.0499, now=10.0,
                      watchdog_ms=50.0) == ""


def test_silence_past_the_timeout_triggers_the_hold():
    assert not controller_silent(None, 100.0, 50.0)  # never heard: nothing to miss
    assert not controller_silent(10.0, 10.0499, 50.0)
    assert controller_silent(10.0, 10.0501, 50.0)
    # the link then answers the controller's next datagram with a hold
    assert hold_cause(new_session=False, resync=True, arrived_at=10.04, now=10.0501,
                      watchdog_ms=50.0) == HOLD_SILENCE


# --------------------------------------------------------------------------- senders

def test_only_the_controller_is_heard():
    assert controller_port(("127.0.0.1", 6511), "127.0.0.1", None) == 6511
    assert controller_port(("127.0.0.1", 6511), "127.0.0.1", 6511) == 6511
    assert controller_port(("127.0.0.1", 7000), "127.0.0.1", 6511) is None  # another port
    assert controller_port(("127.0.0.2", 6511), "127.0.0.1", None) is None  # another host
    assert controller_port(("::1", 6511, 0, 0), "::1", None) == 6511
    for bad in (None, (), ("not-an-ip", 6511), ("127.0.0.1", "x")):
        assert controller_port(bad, "127.0.0.1", None) is None


# --------------------------------------------------------------------------- sequence numbers

def _tracker() -> SequenceTracker:
    return SequenceTracker(reorder_window=8, max_gap=3, min_period_s=0.004, confirm=3,
                           silence_s=0.1)


def test_replayed_and_duplicate_sequence_numbers_are_dropped():
    t = _tracker()
    t0, us = 100.0, 1_700_000_000_000_000
    assert t.decide(1, us, t0).action == NEW_SESSION
    for k in range(2, 40):
        d = t.decide(k, us + 4000 * k, t0 + 0.004 * k)
        assert (d.action, d.missing) == (ACCEPT, 0)
    assert t.decide(39, us + 4000 * 39, t0 + 0.16) == (DROP, "duplicate", 0)
    assert t.decide(36, us + 4000 * 36, t0 + 0.16) == (DROP, "out_of_order", 0)
    # far behind with a clock this session already showed: an old datagram sent again
    assert t.decide(5, us + 4000 * 5, t0 + 0.16) == (DROP, "replayed", 0)
    # the stream goes on; a lost datagram is counted as missing
    assert t.decide(41, us + 4000 * 41, t0 + 0.164) == (ACCEPT, "", 1)


def test_a_far_jump_ahead_needs_the_clock_to_explain_it():
    t = _tracker()
    t.decide(1, 0, 0.0)
    t.decide(2, 4000, 0.004)
    # 1000 sequence numbers ahead 4 ms later: not believed from one datagram
    assert t.decide(1002, 8000, 0.008) == (DROP, "unconfirmed_jump", 0)
    # 10 ahead after 40 ms without datagrams: the controller's clock explains it
    assert t.decide(12, 44_000, 0.044).action == ACCEPT
