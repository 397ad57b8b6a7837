"""The EGM RAPID data channel's layout (torchseam.robot.egm.rapid_data): both ends written and
read back through the wire, an older controller's messages read as absent, malformed data
refused with a reason, never an exception."""

from __future__ import annotations

import math
import struct

import pytest

from torchseam.robot.egm import messages as m
from torchseam.robot.egm import rapid_data as rd
from torchseam.robot.egm.rapid_data import (
    RapidData,
    RapidDataError,
    RapidPhase,
    SensorData,
    SensorState,
)


def _wire(msg):
    """Through the wire: serialised, parsed into a fresh message of the same type."""
    return type(msg).FromString(msg.SerializeToString())


def test_layout_is_the_agreed_one():
    """The indices and values the RAPID module and the simulated controller rely on."""
    assert (rd.SENSOR_SEGMENT, rd.SENSOR_STATE, rd.SENSOR_HEARTBEAT) == (0, 1, 2)
    assert (rd.RAPID_SEGMENT, rd.RAPID_PHASE, rd.RAPID_N_SEGMENTS) == (0, 1, 2)
    assert {s.name: int(s) for s in SensorState} == {"WAIT": 0, "TRACKING": 1, "DONE": 2,
                                                     "ABORT": 3}
    assert {p.name: int(p) for p in RapidPhase} == {"IDLE": 0, "TO_START": 1, "GUIDED": 2,
                                                    "TAKEN_BACK": 3, "ENDED": 4}
    assert rd.HEARTBEAT_MODULO == 2**20
    assert rd.RAPID_CONSTANTS["STATE_ABORT"] == 3 and rd.RAPID_CONSTANTS["PHASE_ENDED"] == 4
    assert rd.RAPID_CONSTANTS["HEARTBEAT_MODULO"] == 2**20


def test_sensor_data_round_trip_and_exact_values():
    data = SensorData(arc_request=True, segment=2, state=SensorState.TRACKING, heartbeat=41)
    msg = m.EgmSensor()
    rd.write_sensor_data(msg, data)
    assert msg.RAPIDtoRobot.digVal is True
    assert list(msg.RAPIDtoRobot.dnum) == [2.0, 1.0, 41.0]  # segment, state, heartbeat
    back = _wire(msg)
    assert rd.read_sensor_data(back) == data
    assert rd.parse_sensor_data(back) == (data, "")
    # writing again replaces, never appends
    later = SensorData(arc_request=False, segment=2, state=SensorState.DONE, heartbeat=42)
    rd.write_sensor_data(msg, later)
    assert list(msg.RAPIDtoRobot.dnum) == [2.0, 2.0, 42.0] and msg.RAPIDtoRobot.digVal is False
    assert rd.read_sensor_data(_wire(msg)) == later


def test_rapid_data_round_trip_and_exact_values():
    data = RapidData(arc_on=True, segment=3, phase=RapidPhase.GUIDED, n_segments=4)
    msg = m.EgmRobot()
    rd.write_rapid_data(msg, data)
    assert msg.RAPIDfromRobot.digVal is True
    assert list(msg.RAPIDfromRobot.dnum) == [3.0, 2.0, 4.0]  # segment, phase, n_segments
    assert rd.parse_rapid_data(_wire(msg)) == (data, "")
    ended = RapidData(arc_on=False, segment=0, phase=RapidPhase.ENDED, n_segments=4)
    rd.write_rapid_data(msg, ended)
    assert rd.read_rapid_data(_wire(msg)) == ended


def test_the_sensor_reply_bytes():
    """An EgmSensor with its RAPID data, byte by byte: field 4, digVal 1, dnum 2."""
    msg = m.EgmSensor()
    rd.write_sensor_data(msg, SensorData(True, 1, SensorState.TRACKING, 5))
    inner = b"\x08\x01" + b"".join(b"\x11" + struct.pack("<d", v) for v in (1.0, 1.0, 5.0))
    assert msg.SerializeToString() == bytes([0x22, len(inner)]) + inner


def test_older_schema_reads_as_absent():
    """A controller on the older schema (or a RAPID program that links no data) sends no
    RAPIDfromRobot: None, reason "absent"; the same for a sensor's reply without it."""
    robot = m.EgmRobot(mciConvergenceMet=True, utilizationRate=3.0)
    robot.header.mtype = m.EgmHeader.MSGTYPE_DATA
    robot = _wire(robot)
    assert rd.read_rapid_data(robot) is None
    assert rd.parse_rapid_data(robot) == (None, "absent")
    sensor = m.EgmSensor()
    sensor.header.seqno = 1
    assert rd.parse_sensor_data(_wire(sensor)) == (None, "absent")


def test_unset_digval_reads_false():
    """digVal is optional: unset, it is False: no arc request, arc not established."""
    msg = m.EgmRobot()
    msg.RAPIDfromRobot.dnum.extend([1.0, 2.0, 2.0])
    assert rd.read_rapid_data(_wire(msg)) == RapidData(False, 1, RapidPhase.GUIDED, 2)
    msg = m.EgmSensor()
    msg.RAPIDtoRobot.dnum.extend([1.0, 1.0, 0.0])
    assert rd.read_sensor_data(_wire(msg)).arc_request is False


def test_extra_values_are_ignored():
    """A RAPID dnum array sends all of its elements (e.g. 40): the layout reads its first."""
    msg = m.EgmRobot()
    msg.RAPIDfromRobot.dnum.extend([2.0, 3.0, 5.0] + [0.0] * 37)
    assert rd.read_rapid_data(_wire(msg)) == RapidData(False, 2, RapidPhase.TAKEN_BACK, 5)


@pytest.mark.parametrize("dnum,reason", [
    ([], "too_few_values"),
    ([1.0, 2.0], "too_few_values"),
    ([1.0, math.nan, 2.0], "non_finite"),
    ([math.inf, 2.0, 2.0], "non_finite"),
    ([1.5, 2.0, 2.0], "non_integral"),
    ([1.0, 2.0000001, 2.0], "non_integral"),
    ([-1.0, 2.0, 2.0], "out_of_range"),
    ([1.0, 2.0, 2.0**20], "out_of_range"),
    ([1.0, 5.0, 2.0], "unknown_phase"),
    ([0.0, 2.0, 2.0], "no_segment"),      # GUIDED, segment 0
    ([0.0, 1.0, 2.0], "no_segment"),      # TO_START, segment 0
])
def test_malformed_rapid_data_is_refused(dnum, reason):
    msg = m.EgmRobot()
    msg.RAPIDfromRobot.dnum.extend(dnum)
    msg = _wire(msg)
    assert rd.parse_rapid_data(msg) == (None, reason)
    assert rd.read_rapid_data(msg) is None


@pytest.mark.parametrize("dnum,reason", [
    ([1.0], "too_few_values"),
    ([1.0, 1.0, math.nan], "non_finite"),
    ([1.0, 1.0, 0.5], "non_integral"),
    ([1.0, 1.0, 2.0**20], "out_of_range"),  # the heartbeat wraps before 2**20
    ([1.0, 4.0, 0.0], "unknown_state"),
    ([0.0, 2.0, 0.0], "no_segment"),        # DONE, segment 0
    ([0.0, 3.0, 0.0], "no_segment"),        # ABORT, segment 0
])
def test_malformed_sensor_data_is_refused(dnum, reason):
    msg = m.EgmSensor()
    msg.RAPIDtoRobot.dnum.extend(dnum)
    msg = _wire(msg)
    assert rd.parse_sensor_data(msg) == (None, reason)
    assert rd.read_sensor_data(msg) is None


def test_between_segments_and_waiting_need_no_segment():
    assert rd.read_sensor_data(_sensor([0.0, 0.0, 7.0])) == SensorData(False, 0,
                                                                       SensorState.WAIT, 7)
    for phase in (RapidPhase.IDLE, RapidPhase.TAKEN_BACK, RapidPhase.ENDED):
        assert RapidData(False, 0, phase, 3).phase is phase


def _sensor(dnum):
    msg = m.EgmSensor()
    msg.RAPIDtoRobot.dnum.extend(dnum)
    return _wire(msg)


@pytest.mark.parametrize("kwargs,reason", [
    ({"heartbeat": 2**20}, "out_of_range"),
    ({"heartbeat": -1}, "out_of_range"),
    ({"segment": 2**20}, "out_of_range"),
    ({"segment": 1.0}, "bad_type"),
    ({"arc_request": 1}, "bad_type"),
    ({"state": 9}, "unknown_state"),
    ({"segment": 0}, "no_segment"),
])
def test_nothing_malformed_can_be_written(kwargs, reason):
    good = {"arc_request": True, "segment": 1, "state": SensorState.TRACKING, "heartbeat": 0}
    with pytest.raises(RapidDataError) as e:
        SensorData(**{**good, **kwargs})
    assert e.value.reason == reason and isinstance(e.value, ValueError)


def test_rapid_data_refuses_bad_values_when_made():
    with pytest.raises(RapidDataError, match="segment"):
        RapidData(False, 2**20, RapidPhase.GUIDED, 3)
    # a program may number its segments as the part does: segment 5 of a 3-segment program
    assert RapidData(False, 5, RapidPhase.GUIDED, 3).segment == 5
    with pytest.raises(RapidDataError, match="phase"):
        RapidData(False, 1, 7, 3)  # type: ignore[arg-type]
    assert RapidData(True, 1, 2, 3).phase is RapidPhase.GUIDED  # type: ignore[arg-type]


def test_heartbeat_wraps():
    assert rd.next_heartbeat(0) == 1
    assert rd.next_heartbeat(2**20 - 1) == 0
    hb = 2**20 - 2
    for _ in range(3):
        hb = rd.next_heartbeat(hb)
        SensorData(False, 0, SensorState.WAIT, hb)  # always writable
    assert hb == 1


def test_reading_never_raises_on_odd_but_parseable_bytes():
    """Whatever dnum a peer sends, the parsers answer (data or a reason), never raise."""
    import random

    rng = random.Random(7)
    specials = [math.nan, math.inf, -math.inf, -0.0, 1e308, 2.0**20, 0.5, 3.0]
    for _ in range(300):
        n = rng.randrange(0, 6)
        dnum = [rng.choice(specials + [float(rng.randrange(-3, 8))]) for _ in range(n)]
        r = m.EgmRobot()
        r.RAPIDfromRobot.digVal = rng.random() < 0.5
        r.RAPIDfromRobot.dnum.extend(dnum)
        data, reason = rd.parse_rapid_data(_wire(r))
        assert (data is None) != (reason == "")
        s = m.EgmSensor()
        s.RAPIDtoRobot.dnum.extend(dnum)
        data2, reason2 = rd.parse_sensor_data(_wire(s))
        assert (data2 is None) != (reason2 == "")
