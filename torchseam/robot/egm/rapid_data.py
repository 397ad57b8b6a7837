"""The EGM RAPID data channel: what the values of ``EgmSensor.RAPIDtoRobot`` and
``EgmRobot.RAPIDfromRobot`` mean to torchseam, in one place for both ends.

The newer EGM schema carries an ``EgmRAPIDdata`` (one bool ``digVal``, a list of numbers
``dnum``) in every message, both ways: RAPID links them to its own signals and ``dnum`` arrays
(``EGMActPose ... \\DIFromSensor \\DOToSensor \\DataFromSensor \\DataToSensor``). torchseam uses
the channel to hand a weld segment over between the RAPID program and the sensor: which segment
runs, who is in charge of the motion, and whether the arc is asked for and burning. The sensor
side (:class:`~torchseam.robot.egm.link.EgmLink`'s ``on_reply`` / ``on_robot``), the simulated
controller and the shipped RAPID module (``torchseam/rapid/TorchseamWeld.mod``, whose CONSTs a
test checks against :data:`RAPID_CONSTANTS`) all take the layout from here.

Layout (``dnum`` indices from 0; RAPID's arrays count from 1, so RAPID reads index ``i`` at
``{i + 1}``):

sensor -> controller, ``EgmSensor.RAPIDtoRobot``
    ``digVal``: arc request (True: the sensor asks for the arc on).
    ``dnum[SENSOR_SEGMENT]``: the segment the sensor works on (1..N, 0 none).
    ``dnum[SENSOR_STATE]``: :class:`SensorState`.
    ``dnum[SENSOR_HEARTBEAT]``: a counter the sensor advances on every reply, modulo
    :data:`HEARTBEAT_MODULO`. The shipped RAPID module switches the arc on only while the
    heartbeat moves, the state is TRACKING and the segment is the one RAPID runs.

controller -> sensor, ``EgmRobot.RAPIDfromRobot``
    ``digVal``: arc on (the welder's arc-established signal).
    ``dnum[RAPID_SEGMENT]``: the segment RAPID runs (1..N, 0 between segments).
    ``dnum[RAPID_PHASE]``: :class:`RapidPhase`.
    ``dnum[RAPID_N_SEGMENTS]``: the number of segments in the program.

The schema's ``digVal`` is a single optional bool (not a list): an unset one reads False, i.e.
"no arc request" / "arc not established", the safe reading at either end. Every number on the
channel is an integer in ``[0, 2**20)``: it travels as a double and lands in a RAPID ``dnum``,
and RAPID code compares it as a ``num`` (a float32, exact for integers up to ``2**24``).

Reading never raises: :func:`parse_sensor_data` / :func:`parse_rapid_data` give
``(data, "")`` or ``(None, reason)``, like :func:`~torchseam.robot.egm.messages.parse_robot`;
:func:`read_sensor_data` / :func:`read_rapid_data` give the data or None. The reason is
``absent`` when the message carries no RAPID data at all (a controller on the older schema, or
one whose RAPID program links no data), else it names what is wrong: ``too_few_values``,
``non_finite``, ``non_integral``, ``out_of_range``, ``unknown_state`` / ``unknown_phase``,
``no_segment`` (a state or phase about a segment with segment 0). More values than the layout
uses are accepted and ignored (a RAPID ``dnum`` array may send all its elements). Writing takes a
:class:`SensorData` / :class:`RapidData`, which refuse bad values when made
(:class:`RapidDataError`), so nothing malformed is ever written.

Usage::

    from torchseam.robot.egm.rapid_data import SensorData, SensorState, write_sensor_data
    write_sensor_data(reply, SensorData(arc_request=True, segment=2,
                                        state=SensorState.TRACKING, heartbeat=hb))
    data, reason = parse_rapid_data(robot_msg)   # None, "absent" from an older controller
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any

#: Every count on the channel (segment numbers, the number of segments, the heartbeat) is an
#: integer in ``[0, COUNT_LIMIT)``.
COUNT_LIMIT = 2**20
#: The heartbeat counts modulo this (it wraps to 0): exact as a RAPID ``num``.
HEARTBEAT_MODULO = COUNT_LIMIT

# dnum indices (from 0) of EgmSensor.RAPIDtoRobot
SENSOR_SEGMENT = 0
SENSOR_STATE = 1
SENSOR_HEARTBEAT = 2
#: how many numbers the sensor writes
SENSOR_DNUM_LEN = 3

# dnum indices (from 0) of EgmRobot.RAPIDfromRobot
RAPID_SEGMENT = 0
RAPID_PHASE = 1
RAPID_N_SEGMENTS = 2
#: how many numbers the controller writes (at least; a longer array is read in part)
RAPID_DNUM_LEN = 3


class RapidDataError(ValueError):
    """A value that does not fit the channel's layout (raised when making the data; the
    parsers catch it and return its reason)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class SensorState(enum.IntEnum):
    """What the sensor says about its segment (``dnum[SENSOR_STATE]``)."""

    #: not ready, or nothing to do: RAPID must not expect guidance
    WAIT = 0
    #: guiding the torch along the segment
    TRACKING = 1
    #: the torch reached the segment's end: RAPID may take the robot back
    DONE = 2
    #: the sensor gives up on the segment (a hold it could not resolve, an operator stop, an
    #: interruption): RAPID takes the robot back, arc off
    ABORT = 3


class RapidPhase(enum.IntEnum):
    """Where the RAPID program is (``dnum[RAPID_PHASE]``)."""

    #: not started
    IDLE = 0
    #: moving to the segment's start on its own path, no EGM motion
    TO_START = 1
    #: EGM motion running: the sensor guides
    GUIDED = 2
    #: the segment is over, RAPID is in charge of the motion
    TAKEN_BACK = 3
    #: the program ended
    ENDED = 4


#: The RAPID module's CONSTs: each must be declared there (``CONST num NAME := value;``) with
#: this value (``tests/test_rapid_module.py`` checks). Indices are the 0-based ones above.
RAPID_CONSTANTS: dict[str, int] = {
    "SENSOR_SEGMENT": SENSOR_SEGMENT,
    "SENSOR_STATE": SENSOR_STATE,
    "SENSOR_HEARTBEAT": SENSOR_HEARTBEAT,
    "RAPID_SEGMENT": RAPID_SEGMENT,
    "RAPID_PHASE": RAPID_PHASE,
    "RAPID_N_SEGMENTS": RAPID_N_SEGMENTS,
    "HEARTBEAT_MODULO": HEARTBEAT_MODULO,
    **{f"STATE_{s.name}": int(s) for s in SensorState},
    **{f"PHASE_{p.name}": int(p) for p in RapidPhase},
}

#: states and phases that are about a segment, so the segment cannot be 0
_STATES_WITH_SEGMENT = frozenset({SensorState.TRACKING, SensorState.DONE, SensorState.ABORT})
_PHASES_WITH_SEGMENT = frozenset({RapidPhase.TO_START, RapidPhase.GUIDED})


def _check_count(name: str, value: int, limit: int = COUNT_LIMIT) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise RapidDataError("bad_type", f"{name}: expected an int, got {value!r}")
    if not 0 <= value < limit:
        raise RapidDataError("out_of_range", f"{name}: expected 0..{limit - 1}, got {value}")


def _check_bool(name: str, value: bool) -> None:
    if not isinstance(value, bool):
        raise RapidDataError("bad_type", f"{name}: expected a bool, got {value!r}")


def _sensor_state(value: int) -> SensorState:
    try:
        return SensorState(value)
    except ValueError:
        raise RapidDataError("unknown_state", f"state: no SensorState {value!r}") from None


def _rapid_phase(value: int) -> RapidPhase:
    try:
        return RapidPhase(value)
    except ValueError:
        raise RapidDataError("unknown_phase", f"phase: no RapidPhase {value!r}") from None


@dataclasses.dataclass(frozen=True)
class SensorData:
    """The sensor's data for RAPID (``EgmSensor.RAPIDtoRobot``).

    Args:
        arc_request: True asks RAPID to switch the arc on.
        segment: the segment the sensor works on, 1..N; 0 none.
        state: the sensor's :class:`SensorState`; TRACKING, DONE and ABORT need a segment.
        heartbeat: the reply counter, ``0 <= heartbeat < HEARTBEAT_MODULO``
            (:func:`next_heartbeat`).

    Raises:
        RapidDataError: a value outside the layout, or of the wrong type (reason
            ``bad_type``; an int that names a state is taken and made a :class:`SensorState`).
    """

    arc_request: bool
    segment: int
    state: SensorState
    heartbeat: int

    def __post_init__(self) -> None:
        _check_bool("arc_request", self.arc_request)
        _check_count("segment", self.segment)
        _check_count("heartbeat", self.heartbeat, HEARTBEAT_MODULO)
        state = _sensor_state(self.state)
        object.__setattr__(self, "state", state)
        if state in _STATES_WITH_SEGMENT and self.segment == 0:
            raise RapidDataError("no_segment", f"state {state.name} needs a segment, got 0")


@dataclasses.dataclass(frozen=True)
class RapidData:
    """The RAPID program's data for the sensor (``EgmRobot.RAPIDfromRobot``).

    Args:
        arc_on: the welder's arc-established signal.
        segment: the segment RAPID runs (1..n_segments in the shipped RAPID module); 0
            between segments. Not checked against ``n_segments``: a program may number its
            segments as the part does (segments 1, 3 and 5 of a part's six, say).
        phase: the program's :class:`RapidPhase`; TO_START and GUIDED need a segment.
        n_segments: the number of segments in the program.

    Raises:
        RapidDataError: a value outside the layout, or of the wrong type (reason
            ``bad_type``).
    """

    arc_on: bool
    segment: int
    phase: RapidPhase
    n_segments: int

    def __post_init__(self) -> None:
        _check_bool("arc_on", self.arc_on)
        _check_count("n_segments", self.n_segments)
        _check_count("segment", self.segment)
        phase = _rapid_phase(self.phase)
        object.__setattr__(self, "phase", phase)
        if phase in _PHASES_WITH_SEGMENT and self.segment == 0:
            raise RapidDataError("no_segment", f"phase {phase.name} needs a segment, got 0")


def next_heartbeat(heartbeat: int) -> int:
    """The heartbeat of the next reply: ``heartbeat + 1`` modulo :data:`HEARTBEAT_MODULO`."""
    return (heartbeat + 1) % HEARTBEAT_MODULO


# --------------------------------------------------------------------------- writing

def write_sensor_data(msg: Any, data: SensorData) -> None:
    """Set ``msg.RAPIDtoRobot`` (``msg``: an ``EgmSensor``) to ``data``, replacing what it held."""
    out = msg.RAPIDtoRobot
    out.Clear()
    out.digVal = data.arc_request
    values = [0.0] * SENSOR_DNUM_LEN
    values[SENSOR_SEGMENT] = float(data.segment)
    values[SENSOR_STATE] = float(data.state)
    values[SENSOR_HEARTBEAT] = float(data.heartbeat)
    out.dnum.extend(values)


def write_rapid_data(msg: Any, data: RapidData) -> None:
    """Set ``msg.RAPIDfromRobot`` (``msg``: an ``EgmRobot``) to ``data``, replacing what it held
    (the simulated controller's side of the channel)."""
    out = msg.RAPIDfromRobot
    out.Clear()
    out.digVal = data.arc_on
    values = [0.0] * RAPID_DNUM_LEN
    values[RAPID_SEGMENT] = float(data.segment)
    values[RAPID_PHASE] = float(data.phase)
    values[RAPID_N_SEGMENTS] = float(data.n_segments)
    out.dnum.extend(values)


# --------------------------------------------------------------------------- reading

def _integers(dnum: Any, n: int) -> list[int]:
    """The first ``n`` numbers as ints; raises :class:`RapidDataError` naming the problem."""
    if len(dnum) < n:
        raise RapidDataError("too_few_values", f"expected at least {n} numbers, got {len(dnum)}")
    values = [float(v) for v in dnum[:n]]
    if not all(math.isfinite(v) for v in values):
        raise RapidDataError("non_finite", f"a number is NaN or infinite: {values}")
    if not all(v.is_integer() for v in values):
        raise RapidDataError("non_integral", f"a number is not an integer: {values}")
    if not all(0 <= v < COUNT_LIMIT for v in values):
        raise RapidDataError("out_of_range", f"a number is outside 0..{COUNT_LIMIT - 1}: "
                                             f"{values}")
    return [int(v) for v in values]


def parse_sensor_data(msg: Any) -> tuple[SensorData | None, str]:
    """Read ``msg.RAPIDtoRobot`` (``msg``: an ``EgmSensor``) as the controller does.

    Returns:
        ``(data, "")``, or ``(None, reason)``: ``absent`` (no RAPID data in the message), or
        what does not fit the layout (see the module's docstring). Never raises.
    """
    if not msg.HasField("RAPIDtoRobot"):
        return None, "absent"
    raw = msg.RAPIDtoRobot
    try:
        v = _integers(raw.dnum, SENSOR_DNUM_LEN)
        return SensorData(arc_request=bool(raw.digVal), segment=v[SENSOR_SEGMENT],
                          state=_sensor_state(v[SENSOR_STATE]),
                          heartbeat=v[SENSOR_HEARTBEAT]), ""
    except RapidDataError as e:
        return None, e.reason


def parse_rapid_data(msg: Any) -> tuple[RapidData | None, str]:
    """Read ``msg.RAPIDfromRobot`` (``msg``: an ``EgmRobot``) as the sensor does.

    Returns:
        ``(data, "")``, or ``(None, reason)``: ``absent`` (a controller on the older schema, or a
        RAPID program that links no data), or what does not fit the layout (see the module's
        docstring). Never raises.
    """
    if not msg.HasField("RAPIDfromRobot"):
        return None, "absent"
    raw = msg.RAPIDfromRobot
    try:
        v = _integers(raw.dnum, RAPID_DNUM_LEN)
        return RapidData(arc_on=bool(raw.digVal), segment=v[RAPID_SEGMENT],
                         phase=_rapid_phase(v[RAPID_PHASE]),
                         n_segments=v[RAPID_N_SEGMENTS]), ""
    except RapidDataError as e:
        return None, e.reason


def read_sensor_data(msg: Any) -> SensorData | None:
    """The sensor's data in an ``EgmSensor``, or None (absent or malformed: the reason is
    :func:`parse_sensor_data`'s)."""
    return parse_sensor_data(msg)[0]


def read_rapid_data(msg: Any) -> RapidData | None:
    """The RAPID program's data in an ``EgmRobot``, or None (absent: a controller on the older
    schema; malformed: the reason is :func:`parse_rapid_data`'s)."""
    return parse_rapid_data(msg)[0]


__all__ = ["COUNT_LIMIT", "HEARTBEAT_MODULO", "RAPID_CONSTANTS", "RAPID_DNUM_LEN",
           "RAPID_N_SEGMENTS", "RAPID_PHASE", "RAPID_SEGMENT", "SENSOR_DNUM_LEN",
           "SENSOR_HEARTBEAT", "SENSOR_SEGMENT", "SENSOR_STATE", "RapidData", "RapidDataError",
           "RapidPhase", "SensorData", "SensorState", "next_heartbeat", "parse_rapid_data",
           "parse_sensor_data", "read_rapid_data", "read_sensor_data", "write_rapid_data",
           "write_sensor_data"]
