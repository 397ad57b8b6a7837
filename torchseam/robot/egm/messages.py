"""Protobuf message classes of ABB EGM (package ``abb.egm``, proto2), built without protoc, and
the parsers that turn one datagram into a validated message (:func:`parse_robot`,
:func:`parse_sensor`: size, type, required fields, finite values) without ever raising.

The schema lives in one table below, written from ABB's egm.proto (sensor interface V1.1) plus
the newer schema's optional fields (``RAPIDtoRobot`` / ``RAPIDfromRobot``, the data channel
between the sensor and the RAPID program, and ``moveIndex``, ``CollisionInfo``; the proto file
names the published file they come from); the readable ``egm.proto`` next to this file says the
same thing, and a test compiles that file with ``grpc_tools.protoc`` and checks the two agree
descriptor by descriptor and byte by byte. What the RAPID data's values mean is
:mod:`torchseam.robot.egm.rapid_data`'s.

Why a table and not generated ``*_pb2.py``: generated code is tied to the protoc version that
wrote it (newer gencode is refused by an older runtime, very old gencode by a newer one), while a
``FileDescriptorProto`` built here works with any protobuf runtime >= 4.21 and needs nothing but
the ``protobuf`` package at run time.

The classes live in a private descriptor pool, so they never clash with another ``abb.egm``
module (e.g. ABB's own generated ``egm_pb2``) imported into the same process.

Usage::

    from torchseam.robot.egm.messages import EgmRobot, EgmHeader
    msg = EgmRobot()
    msg.header.mtype = EgmHeader.MSGTYPE_DATA
    data = msg.SerializeToString()
"""

from __future__ import annotations

import math
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message

PACKAGE = "abb.egm"
#: File name the descriptors are registered under (matches ``protoc -I <dir> egm.proto``).
PROTO_FILE = "egm.proto"

_F = descriptor_pb2.FieldDescriptorProto
_SCALARS = {
    "double": _F.TYPE_DOUBLE,
    "uint32": _F.TYPE_UINT32,
    "uint64": _F.TYPE_UINT64,
    "bool": _F.TYPE_BOOL,
}
_LABELS = {"optional": _F.LABEL_OPTIONAL, "required": _F.LABEL_REQUIRED,
           "repeated": _F.LABEL_REPEATED}

# (message, nested enums {name: [(value name, number)]},
#  fields [(label, type, name, number, default or None)])
# A type that is not a scalar names a message of this package or a "Message.Enum".
SCHEMA: tuple[tuple[str, dict[str, list[tuple[str, int]]],
                    list[tuple[str, str, str, int, str | None]]], ...] = (
    ("EgmHeader",
     {"MessageType": [("MSGTYPE_UNDEFINED", 0), ("MSGTYPE_COMMAND", 1), ("MSGTYPE_DATA", 2),
                      ("MSGTYPE_CORRECTION", 3), ("MSGTYPE_PATH_CORRECTION", 4)]},
     [("optional", "uint32", "seqno", 1, None),
      ("optional", "uint32", "tm", 2, None),
      ("optional", "EgmHeader.MessageType", "mtype", 3, "MSGTYPE_UNDEFINED")]),
    ("EgmCartesian", {},
     [("required", "double", "x", 1, None), ("required", "double", "y", 2, None),
      ("required", "double", "z", 3, None)]),
    ("EgmQuaternion", {},
     [("required", "double", "u0", 1, None), ("required", "double", "u1", 2, None),
      ("required", "double", "u2", 3, None), ("required", "double", "u3", 4, None)]),
    ("EgmEuler", {},
     [("required", "double", "x", 1, None), ("required", "double", "y", 2, None),
      ("required", "double", "z", 3, None)]),
    ("EgmClock", {},
     [("required", "uint64", "sec", 1, None), ("required", "uint64", "usec", 2, None)]),
    ("EgmPose", {},
     [("optional", "EgmCartesian", "pos", 1, None),
      ("optional", "EgmQuaternion", "orient", 2, None),
      ("optional", "EgmEuler", "euler", 3, None)]),
    ("EgmJoints", {}, [("repeated", "double", "joints", 1, None)]),
    ("EgmCartesianSpeed", {}, [("repeated", "double", "value", 1, None)]),
    ("EgmPlanned", {},
     [("optional", "EgmJoints", "joints", 1, None),
      ("optional", "EgmPose", "cartesian", 2, None),
      ("optional", "EgmJoints", "externalJoints", 3, None),
      ("optional", "EgmClock", "time", 4, None)]),
    ("EgmFeedBack", {},
     [("optional", "EgmJoints", "joints", 1, None),
      ("optional", "EgmPose", "cartesian", 2, None),
      ("optional", "EgmJoints", "externalJoints", 3, None),
      ("optional", "EgmClock", "time", 4, None)]),
    ("EgmSpeedRef", {},
     [("optional", "EgmJoints", "joints", 1, None),
      ("optional", "EgmCartesianSpeed", "cartesians", 2, None),
      ("optional", "EgmJoints", "externalJoints", 3, None)]),
    ("EgmPathCorr", {},
     [("required", "EgmCartesian", "pos", 1, None),
      ("required", "uint32", "age", 2, None)]),
    ("EgmMotorState",
     {"MotorStateType": [("MOTORS_UNDEFINED", 0), ("MOTORS_ON", 1), ("MOTORS_OFF", 2)]},
     [("required", "EgmMotorState.MotorStateType", "state", 1, None)]),
    ("EgmMCIState",
     {"MCIStateType": [("MCI_UNDEFINED", 0), ("MCI_ERROR", 1), ("MCI_STOPPED", 2),
                       ("MCI_RUNNING", 3)]},
     [("required", "EgmMCIState.MCIStateType", "state", 1, "MCI_UNDEFINED")]),
    ("EgmRapidCtrlExecState",
     {"RapidCtrlExecStateType": [("RAPID_UNDEFINED", 0), ("RAPID_STOPPED", 1),
                                 ("RAPID_RUNNING", 2)]},
     [("required", "EgmRapidCtrlExecState.RapidCtrlExecStateType", "state", 1,
       "RAPID_UNDEFINED")]),
    ("EgmTestSignals", {}, [("repeated", "double", "signals", 1, None)]),
    ("EgmMeasuredForce", {}, [("repeated", "double", "force", 1, None)]),
    # the newer schema (egm.proto says where from): collision info and the RAPID data channel
    ("EgmCollisionInfo", {},
     [("optional", "bool", "collsionTriggered", 1, None),  # ABB's spelling
      ("repeated", "double", "collDetQuota", 2, None)]),
    ("EgmRAPIDdata", {},
     [("optional", "bool", "digVal", 1, None),
      ("repeated", "double", "dnum", 2, None)]),
    ("EgmRobot", {},
     [("optional", "EgmHeader", "header", 1, None),
      ("optional", "EgmFeedBack", "feedBack", 2, None),
      ("optional", "EgmPlanned", "planned", 3, None),
      ("optional", "EgmMotorState", "motorState", 4, None),
      ("optional", "EgmMCIState", "mciState", 5, None),
      ("optional", "bool", "mciConvergenceMet", 6, None),
      ("optional", "EgmTestSignals", "testSignals", 7, None),
      ("optional", "EgmRapidCtrlExecState", "rapidExecState", 8, None),
      ("optional", "EgmMeasuredForce", "measuredForce", 9, None),
      ("optional", "double", "utilizationRate", 10, None),
      ("optional", "uint32", "moveIndex", 11, None),
      ("optional", "EgmCollisionInfo", "CollisionInfo", 12, None),
      ("optional", "EgmRAPIDdata", "RAPIDfromRobot", 13, None)]),
    ("EgmSensor", {},
     [("optional", "EgmHeader", "header", 1, None),
      ("optional", "EgmPlanned", "planned", 2, None),
      ("optional", "EgmSpeedRef", "speedRef", 3, None),
      ("optional", "EgmRAPIDdata", "RAPIDtoRobot", 4, None)]),
    ("EgmSensorPathCorr", {},
     [("optional", "EgmHeader", "header", 1, None),
      ("optional", "EgmPathCorr", "pathCorr", 2, None)]),
)

MESSAGE_NAMES: tuple[str, ...] = tuple(name for name, _, _ in SCHEMA)


def file_descriptor_proto() -> descriptor_pb2.FileDescriptorProto:
    """The ``egm.proto`` file as a ``FileDescriptorProto`` (what ``protoc`` would produce)."""
    # syntax left unset: that means proto2, and it is what protoc writes for a proto2 file.
    fdp = descriptor_pb2.FileDescriptorProto(name=PROTO_FILE, package=PACKAGE)
    enum_names = {f"{msg}.{enum}" for msg, enums, _ in SCHEMA for enum in enums}
    for msg_name, enums, fields in SCHEMA:
        msg = fdp.message_type.add(name=msg_name)
        for enum_name, values in enums.items():
            enum = msg.enum_type.add(name=enum_name)
            for value_name, number in values:
                enum.value.add(name=value_name, number=number)
        for label, type_, name, number, default in fields:
            # json_name as protoc fills it in (lowerCamelCase; these names have no '_').
            field = msg.field.add(name=name, number=number, label=_LABELS[label],
                                  json_name=name)
            if type_ in _SCALARS:
                field.type = _SCALARS[type_]
            elif type_ in enum_names:
                field.type = _F.TYPE_ENUM
                field.type_name = f".{PACKAGE}.{type_}"
            else:
                field.type = _F.TYPE_MESSAGE
                field.type_name = f".{PACKAGE}.{type_}"
            if default is not None:
                field.default_value = default
    return fdp


def _build() -> dict[str, type[Message]]:
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file_descriptor_proto())
    return {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(
        f"{PACKAGE}.{name}")) for name in MESSAGE_NAMES}


CLASSES: dict[str, type[Message]] = _build()

# Module attributes typed as Any: the classes are made at run time, so a type checker cannot
# see their fields.
EgmHeader: Any = CLASSES["EgmHeader"]
EgmCartesian: Any = CLASSES["EgmCartesian"]
EgmQuaternion: Any = CLASSES["EgmQuaternion"]
EgmEuler: Any = CLASSES["EgmEuler"]
EgmClock: Any = CLASSES["EgmClock"]
EgmPose: Any = CLASSES["EgmPose"]
EgmJoints: Any = CLASSES["EgmJoints"]
EgmCartesianSpeed: Any = CLASSES["EgmCartesianSpeed"]
EgmPlanned: Any = CLASSES["EgmPlanned"]
EgmFeedBack: Any = CLASSES["EgmFeedBack"]
EgmSpeedRef: Any = CLASSES["EgmSpeedRef"]
EgmPathCorr: Any = CLASSES["EgmPathCorr"]
EgmMotorState: Any = CLASSES["EgmMotorState"]
EgmMCIState: Any = CLASSES["EgmMCIState"]
EgmRapidCtrlExecState: Any = CLASSES["EgmRapidCtrlExecState"]
EgmTestSignals: Any = CLASSES["EgmTestSignals"]
EgmMeasuredForce: Any = CLASSES["EgmMeasuredForce"]
EgmCollisionInfo: Any = CLASSES["EgmCollisionInfo"]
EgmRAPIDdata: Any = CLASSES["EgmRAPIDdata"]
EgmRobot: Any = CLASSES["EgmRobot"]
EgmSensor: Any = CLASSES["EgmSensor"]
EgmSensorPathCorr: Any = CLASSES["EgmSensorPathCorr"]


# --------------------------------------------------------------------------- parsing datagrams

def _finite(values: Any) -> bool:
    return all(map(math.isfinite, values))


def _pose_values(pose: Any) -> list[float]:
    out: list[float] = []
    if pose.HasField("pos"):
        out += (pose.pos.x, pose.pos.y, pose.pos.z)
    if pose.HasField("orient"):
        o = pose.orient
        out += (o.u0, o.u1, o.u2, o.u3)
    if pose.HasField("euler"):
        out += (pose.euler.x, pose.euler.y, pose.euler.z)
    return out


def _check_size(data: bytes, max_bytes: int) -> str:
    if not data:
        return "empty"
    if len(data) > max_bytes:
        return "oversized"
    return ""


def parse_robot(data: bytes, max_bytes: int = 1024) -> tuple[Any | None, str]:
    """Parse and validate one datagram as ``EgmRobot``.

    Returns:
        ``(message, "")`` or ``(None, reason)`` with reason one of ``empty``, ``oversized``,
        ``unparseable``, ``wrong_type`` (no header or ``mtype`` is not ``MSGTYPE_DATA``; the
        protocol is not self-describing, so an ``EgmSensor`` would otherwise parse as an
        ``EgmRobot``), ``missing_required`` (a required field is absent: the protobuf runtime
        does not check nested ones while parsing), ``non_finite`` (a NaN or inf in a joint or
        pose value). Never raises.
    """
    reason = _check_size(data, max_bytes)
    if reason:
        return None, reason
    msg = EgmRobot()
    try:
        msg.ParseFromString(data)
    except Exception:  # DecodeError, missing required fields, anything the runtime raises
        return None, "unparseable"
    if not msg.HasField("header") or msg.header.mtype != EgmHeader.MSGTYPE_DATA:
        return None, "wrong_type"
    if not msg.IsInitialized():  # the runtime's parser does not check nested required fields
        return None, "missing_required"
    values: list[float] = []
    for part in (msg.feedBack, msg.planned):
        values += part.joints.joints
        values += part.externalJoints.joints
        values += _pose_values(part.cartesian)
    if not _finite(values):
        return None, "non_finite"
    return msg, ""


def parse_sensor(data: bytes, mode: str, max_bytes: int = 1024) -> tuple[Any | None, str]:
    """Parse and validate one sensor reply (``EgmSensor`` for ``pose``, ``EgmSensorPathCorr``
    for ``pathcorr``), as the controller side does.

    Returns ``(message, "")`` or ``(None, reason)``: ``empty``, ``oversized``, ``unparseable``,
    ``wrong_type`` (``mtype`` not ``MSGTYPE_CORRECTION`` / ``MSGTYPE_PATH_CORRECTION``),
    ``missing_required``, ``incomplete`` (no pose / no correction), ``non_finite``. Never raises.
    """
    reason = _check_size(data, max_bytes)
    if reason:
        return None, reason
    pose_mode = mode == "pose"
    msg = EgmSensor() if pose_mode else EgmSensorPathCorr()
    try:
        msg.ParseFromString(data)
    except Exception:
        return None, "unparseable"
    want = EgmHeader.MSGTYPE_CORRECTION if pose_mode else EgmHeader.MSGTYPE_PATH_CORRECTION
    if not msg.HasField("header") or msg.header.mtype != want:
        return None, "wrong_type"
    if not msg.IsInitialized():
        return None, "missing_required"
    if pose_mode:
        c = msg.planned.cartesian
        if not (msg.HasField("planned") and msg.planned.HasField("cartesian")
                and c.HasField("pos") and (c.HasField("orient") or c.HasField("euler"))):
            return None, "incomplete"
        values = _pose_values(c)
    else:
        if not msg.HasField("pathCorr"):
            return None, "incomplete"
        p = msg.pathCorr.pos
        values = [p.x, p.y, p.z]
    if not _finite(values):
        return None, "non_finite"
    return msg, ""


__all__ = ["CLASSES", "MESSAGE_NAMES", "PACKAGE", "PROTO_FILE", "SCHEMA",
           "file_descriptor_proto", "parse_robot", "parse_sensor", *MESSAGE_NAMES]
