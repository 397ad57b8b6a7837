"""ABB EGM message classes: the wire schema of ABB's egm.proto, round trips, and agreement with
the shipped egm.proto compiled by protoc."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, text_format
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import DecodeError, EncodeError

from torchseam.robot.egm import messages as m
from torchseam.robot.egm import parse_robot, parse_sensor

PROTO = Path(m.__file__).with_name("egm.proto")

# ABB's egm.proto field table, transcribed independently of egm.messages.SCHEMA:
# message -> [(field, number, type, label)]; label o(ptional) / r(equired) / * (repeated).
ROBOT_MD = {
    "EgmHeader": [("seqno", 1, "uint32", "o"), ("tm", 2, "uint32", "o"),
                  ("mtype", 3, "EgmHeader.MessageType", "o")],
    "EgmCartesian": [("x", 1, "double", "r"), ("y", 2, "double", "r"), ("z", 3, "double", "r")],
    "EgmQuaternion": [("u0", 1, "double", "r"), ("u1", 2, "double", "r"),
                      ("u2", 3, "double", "r"), ("u3", 4, "double", "r")],
    "EgmEuler": [("x", 1, "double", "r"), ("y", 2, "double", "r"), ("z", 3, "double", "r")],
    "EgmClock": [("sec", 1, "uint64", "r"), ("usec", 2, "uint64", "r")],
    "EgmPose": [("pos", 1, "EgmCartesian", "o"), ("orient", 2, "EgmQuaternion", "o"),
                ("euler", 3, "EgmEuler", "o")],
    "EgmJoints": [("joints", 1, "double", "*")],
    "EgmCartesianSpeed": [("value", 1, "double", "*")],
    "EgmPlanned": [("joints", 1, "EgmJoints", "o"), ("cartesian", 2, "EgmPose", "o"),
                   ("externalJoints", 3, "EgmJoints", "o"), ("time", 4, "EgmClock", "o")],
    "EgmFeedBack": [("joints", 1, "EgmJoints", "o"), ("cartesian", 2, "EgmPose", "o"),
                    ("externalJoints", 3, "EgmJoints", "o"), ("time", 4, "EgmClock", "o")],
    "EgmSpeedRef": [("joints", 1, "EgmJoints", "o"), ("cartesians", 2, "EgmCartesianSpeed", "o"),
                    ("externalJoints", 3, "EgmJoints", "o")],
    "EgmPathCorr": [("pos", 1, "EgmCartesian", "r"), ("age", 2, "uint32", "r")],
    "EgmMotorState": [("state", 1, "EgmMotorState.MotorStateType", "r")],
    "EgmMCIState": [("state", 1, "EgmMCIState.MCIStateType", "r")],
    "EgmRapidCtrlExecState": [("state", 1, "EgmRapidCtrlExecState.RapidCtrlExecStateType", "r")],
    "EgmTestSignals": [("signals", 1, "double", "*")],
    "EgmMeasuredForce": [("force", 1, "double", "*")],
    "EgmRobot": [("header", 1, "EgmHeader", "o"), ("feedBack", 2, "EgmFeedBack", "o"),
                 ("planned", 3, "EgmPlanned", "o"), ("motorState", 4, "EgmMotorState", "o"),
                 ("mciState", 5, "EgmMCIState", "o"), ("mciConvergenceMet", 6, "bool", "o"),
                 ("testSignals", 7, "EgmTestSignals", "o"),
                 ("rapidExecState", 8, "EgmRapidCtrlExecState", "o"),
                 ("measuredForce", 9, "EgmMeasuredForce", "o"),
                 ("utilizationRate", 10, "double", "o")],
    "EgmSensor": [("header", 1, "EgmHeader", "o"), ("planned", 2, "EgmPlanned", "o"),
                  ("speedRef", 3, "EgmSpeedRef", "o")],
    "EgmSensorPathCorr": [("header", 1, "EgmHeader", "o"), ("pathCorr", 2, "EgmPathCorr", "o")],
}
# The newer schema's fields, transcribed from the published egm.proto that egm.proto's header
# names (macs-lab/abb-egm-with-python, egm.proto): message -> [(field, number, type, label)];
# the fields of a message ROBOT_MD has too are added to its list.
NEWER = {
    "EgmCollisionInfo": [("collsionTriggered", 1, "bool", "o"), ("collDetQuota", 2, "double", "*")],
    "EgmRAPIDdata": [("digVal", 1, "bool", "o"), ("dnum", 2, "double", "*")],
    "EgmRobot": [("moveIndex", 11, "uint32", "o"), ("CollisionInfo", 12, "EgmCollisionInfo", "o"),
                 ("RAPIDfromRobot", 13, "EgmRAPIDdata", "o")],
    "EgmSensor": [("RAPIDtoRobot", 4, "EgmRAPIDdata", "o")],
}
SCHEMA_TABLE = {name: ROBOT_MD.get(name, []) + NEWER.get(name, [])
                for name in [*ROBOT_MD, *NEWER]}
ENUMS = {
    "EgmHeader.MessageType": {0: "UNDEFINED", 1: "COMMAND", 2: "DATA", 3: "CORRECTION",
                              4: "PATH_CORRECTION"},
    "EgmMotorState.MotorStateType": {0: "UNDEFINED", 1: "ON", 2: "OFF"},
    "EgmMCIState.MCIStateType": {0: "UNDEFINED", 1: "ERROR", 2: "STOPPED", 3: "RUNNING"},
    "EgmRapidCtrlExecState.RapidCtrlExecStateType": {0: "UNDEFINED", 1: "STOPPED", 2: "RUNNING"},
}
_SCALAR_NAMES = {FieldDescriptor.TYPE_DOUBLE: "double", FieldDescriptor.TYPE_UINT32: "uint32",
                 FieldDescriptor.TYPE_UINT64: "uint64", FieldDescriptor.TYPE_BOOL: "bool"}


def _label(f: FieldDescriptor) -> str:
    return "*" if f.is_repeated else "r" if f.is_required else "o"


def _type_name(f: FieldDescriptor) -> str:
    if f.type in _SCALAR_NAMES:
        return _SCALAR_NAMES[f.type]
    desc = f.message_type or f.enum_type
    return desc.full_name.removeprefix("abb.egm.")


def _fill(msg, k: int = 0):
    """Set every field of ``msg`` (recursively) to a distinct non-default value."""
    for f in msg.DESCRIPTOR.fields:
        k += 1
        if f.type == FieldDescriptor.TYPE_MESSAGE:
            _fill(getattr(msg, f.name), k * 10)
        elif f.is_repeated:
            getattr(msg, f.name).extend([k + 0.5, -2.25 * k, 1e-3, 6.0])
        elif f.type == FieldDescriptor.TYPE_DOUBLE:
            setattr(msg, f.name, k * 1.25 - 0.001)
        elif f.type == FieldDescriptor.TYPE_UINT32:
            setattr(msg, f.name, 4_000_000_000 - k)  # above 2^31: unsigned on the wire
        elif f.type == FieldDescriptor.TYPE_UINT64:
            setattr(msg, f.name, 2**40 + k)
        elif f.type == FieldDescriptor.TYPE_BOOL:
            setattr(msg, f.name, True)
        elif f.type == FieldDescriptor.TYPE_ENUM:
            setattr(msg, f.name, f.enum_type.values[-1].number)
    return msg


def test_schema_matches_robot_md_field_table():
    """ABB's field table (RobotWare 6), plus the newer schema's optional fields as published."""
    assert set(m.MESSAGE_NAMES) == set(SCHEMA_TABLE)
    for name, fields in SCHEMA_TABLE.items():
        desc = m.CLASSES[name].DESCRIPTOR
        assert desc.full_name == f"abb.egm.{name}"
        got = [(f.name, f.number, _type_name(f), _label(f)) for f in desc.fields]
        assert not any(f.is_packed for f in desc.fields), "proto2 repeated fields are unpacked"
        assert sorted(got, key=lambda x: x[1]) == fields, name
    for full, values in ENUMS.items():
        msg, enum = full.split(".")
        ed = m.CLASSES[msg].DESCRIPTOR.enum_types_by_name[enum]
        assert {v.number: v.name.split("_", 1)[1] for v in ed.values} == values


@pytest.mark.parametrize("name", m.MESSAGE_NAMES)
def test_round_trip_every_message_type(name):
    cls = m.CLASSES[name]
    msg = _fill(cls())
    assert len(msg.ListFields()) == len(cls.DESCRIPTOR.fields)  # nothing left at default
    data = msg.SerializeToString(deterministic=True)
    back = cls.FromString(data)
    assert back == msg
    assert back.SerializeToString(deterministic=True) == data
    if not any(f.is_required for f in cls.DESCRIPTOR.fields):
        assert cls.FromString(b"") == cls()


def test_known_wire_bytes():
    """Bytes worked out by hand from the field numbers and proto2 encoding rules."""
    h = m.EgmHeader(seqno=1, tm=2, mtype=m.EgmHeader.MSGTYPE_DATA)
    assert h.SerializeToString() == bytes([0x08, 1, 0x10, 2, 0x18, 2])
    pc = m.EgmSensorPathCorr()
    pc.header.mtype = m.EgmHeader.MSGTYPE_PATH_CORRECTION
    pc.pathCorr.pos.x, pc.pathCorr.pos.y, pc.pathCorr.pos.z = 1.0, -2.0, 0.5
    pc.pathCorr.age = 300
    cart = b"".join(bytes([tag]) + struct.pack("<d", v)
                    for tag, v in ((0x09, 1.0), (0x11, -2.0), (0x19, 0.5)))
    path_corr = bytes([0x0A, len(cart)]) + cart + bytes([0x10, 0xAC, 0x02])  # 300 as a varint
    assert pc.SerializeToString() == (bytes([0x0A, 2, 0x18, 4])
                                      + bytes([0x12, len(path_corr)]) + path_corr)
    r = m.EgmRobot(mciConvergenceMet=True, utilizationRate=12.5)
    assert r.SerializeToString() == bytes([0x30, 1, 0x51]) + struct.pack("<d", 12.5)
    # proto2 repeated doubles are not packed: one tag per value
    j = m.EgmJoints(joints=[1.0, 2.0])
    assert j.SerializeToString() == b"\x09" + struct.pack("<d", 1.0) + b"\x09" + struct.pack(
        "<d", 2.0)
    # ...and a packed encoding from another implementation parses all the same
    packed = b"\x0a\x10" + struct.pack("<dd", 1.0, 2.0)
    assert list(m.EgmJoints.FromString(packed).joints) == [1.0, 2.0]


def test_rapid_data_wire_bytes():
    """The RAPID data channel at the published field numbers: EgmSensor.RAPIDtoRobot 4,
    EgmRobot.RAPIDfromRobot 13, EgmRAPIDdata digVal 1 (varint), dnum 2 (doubles, unpacked)."""
    s = m.EgmSensor()
    s.RAPIDtoRobot.digVal = True
    s.RAPIDtoRobot.dnum.extend([2.0, 1.0])
    inner = (bytes([0x08, 1]) + b"\x11" + struct.pack("<d", 2.0)
             + b"\x11" + struct.pack("<d", 1.0))
    assert s.SerializeToString() == bytes([0x22, len(inner)]) + inner  # field 4, length-delim.
    r = m.EgmRobot()
    r.RAPIDfromRobot.digVal = False
    r.RAPIDfromRobot.dnum.append(3.0)
    inner = bytes([0x08, 0]) + b"\x11" + struct.pack("<d", 3.0)
    assert r.SerializeToString() == bytes([0x6A, len(inner)]) + inner  # field 13
    r2 = m.EgmRobot(moveIndex=7)
    r2.CollisionInfo.collsionTriggered = True
    assert r2.SerializeToString() == bytes([0x58, 7, 0x62, 2, 0x08, 1])  # fields 11 and 12
    # the bytes another client wrote (moveIndex 7, RAPIDfromRobot {digVal: true}) parse
    back = m.EgmRobot.FromString(b"\x58\x07" + b"\x6a\x02\x08\x01")
    assert back.moveIndex == 7 and back.RAPIDfromRobot.digVal is True
    assert list(back.RAPIDfromRobot.dnum) == []


def test_messages_of_the_older_schema_still_parse():
    """A controller (or sensor) on the older schema sends no RAPID data: its messages parse,
    the new fields absent; and a newer controller's EgmMeasuredForce (fcActive = 1, force = 2
    there, force = 1 here) parses too, its values left unknown."""
    old = m.EgmRobot(mciConvergenceMet=True, utilizationRate=12.5)
    old.header.mtype = m.EgmHeader.MSGTYPE_DATA
    msg, reason = parse_robot(old.SerializeToString())
    assert reason == "" and not msg.HasField("RAPIDfromRobot") and not msg.HasField("moveIndex")
    sensor = m.EgmSensor()
    sensor.header.mtype = m.EgmHeader.MSGTYPE_CORRECTION
    sensor.planned.cartesian.pos.x = sensor.planned.cartesian.pos.y = 1.0
    sensor.planned.cartesian.pos.z = 1.0
    q = sensor.planned.cartesian.orient
    q.u0, q.u1, q.u2, q.u3 = 1.0, 0.0, 0.0, 0.0
    msg, reason = parse_sensor(sensor.SerializeToString(), "pose")
    assert reason == "" and not msg.HasField("RAPIDtoRobot")
    force = b"\x08\x01" + b"\x11" + struct.pack("<d", 5.0)
    newer = m.EgmRobot.FromString(bytes([0x4A, len(force)]) + force)
    assert newer.HasField("measuredForce") and list(newer.measuredForce.force) == []


def test_required_fields_are_enforced():
    c = m.EgmCartesian(x=1.0, y=2.0)
    with pytest.raises(EncodeError):  # the writer refuses an incomplete message
        c.SerializeToString()
    # the reader does not check nested required fields (upb): a path correction without its
    # age parses, with age reading 0; the link's parsers catch it through IsInitialized
    p = m.EgmSensorPathCorr()
    p.header.mtype = m.EgmHeader.MSGTYPE_PATH_CORRECTION
    p.pathCorr.pos.x = p.pathCorr.pos.y = p.pathCorr.pos.z = 0.0
    data = p.SerializePartialToString()
    try:
        parsed = m.EgmSensorPathCorr.FromString(data)
    except DecodeError:
        parsed = None
    assert parsed is None or not parsed.IsInitialized()
    assert parse_sensor(data, "pathcorr") == (None, "missing_required")
    r = m.EgmRobot()
    r.header.mtype = m.EgmHeader.MSGTYPE_DATA
    r.motorState.SetInParent()  # state is required
    assert parse_robot(r.SerializePartialToString()) == (None, "missing_required")


def test_classes_live_in_a_private_pool():
    # ABB's own generated egm_pb2 could be imported next to ours without a clash
    with pytest.raises(KeyError):
        descriptor_pool.Default().FindMessageTypeByName("abb.egm.EgmRobot")


def test_the_wheel_ships_the_proto():
    """egm.proto lies next to the messages module and pyproject's package-data names it, so the
    wheel carries it (.ci/run compares the installed copy)."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    root = Path(__file__).resolve().parents[1]
    globs = tomllib.loads((root / "pyproject.toml").read_text())[
        "tool"]["setuptools"]["package-data"]["torchseam"]
    pkg = root / "torchseam"
    assert PROTO.is_file() and PROTO.parent == Path(m.__file__).parent
    assert any(PROTO.resolve() in {p.resolve() for p in pkg.glob(g)} for g in globs)


# --------------------------------------------------------------------------- against protoc

@pytest.fixture(scope="module")
def protoc_descriptor(tmp_path_factory) -> descriptor_pb2.FileDescriptorProto:
    protoc = pytest.importorskip(
        "grpc_tools.protoc", reason="grpcio-tools is not installed: cannot compile egm.proto")
    out = tmp_path_factory.mktemp("protoc") / "egm.pb"
    rc = protoc.main(["grpc_tools.protoc", f"-I{PROTO.parent}", f"--descriptor_set_out={out}",
                      PROTO.name])
    assert rc == 0, f"protoc failed on {PROTO}"
    fds = descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes())
    assert len(fds.file) == 1
    return fds.file[0]


def test_committed_proto_and_runtime_descriptors_agree(protoc_descriptor):
    ours = m.file_descriptor_proto()
    if protoc_descriptor != ours:  # show what differs, not just "not equal"
        a = text_format.MessageToString(protoc_descriptor).splitlines()
        b = text_format.MessageToString(ours).splitlines()
        import difflib

        diff = "\n".join(difflib.unified_diff(a, b, "protoc egm.proto", "egm.messages", n=2))
        pytest.fail(f"egm.proto and egm.messages.SCHEMA differ:\n{diff}")


@pytest.mark.parametrize("name", m.MESSAGE_NAMES)
def test_bytes_cross_parse_with_protoc_classes(protoc_descriptor, name):
    pool = descriptor_pool.DescriptorPool()
    pool.Add(protoc_descriptor)
    theirs = message_factory.GetMessageClass(pool.FindMessageTypeByName(f"abb.egm.{name}"))
    ours = m.CLASSES[name]
    # same bytes both ways, and the same field names and values (an unknown field would print
    # as a bare number in text format)
    msg = _fill(ours())
    data = msg.SerializeToString(deterministic=True)
    parsed = theirs.FromString(data)
    assert parsed.SerializeToString(deterministic=True) == data
    assert text_format.MessageToString(parsed) == text_format.MessageToString(msg)
    msg2 = _fill(theirs(), 7)
    data2 = msg2.SerializeToString(deterministic=True)
    parsed2 = ours.FromString(data2)
    assert parsed2.SerializeToString(deterministic=True) == data2
    assert text_format.MessageToString(parsed2) == text_format.MessageToString(msg2)
