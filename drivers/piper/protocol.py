"""The PiPER CAN protocol: pure encode/decode of every frame, both directions, in SI units.

Sources: piper_sdk 0.6.x (``protocol_v2/piper_protocol_v2.py``, ``piper_msgs/msg_v2``); every
layout is in the project's ``reference/piper_can.md`` §1.2-1.6. Classic CAN, 11-bit IDs, all
multi-byte fields big-endian.

    >>> frame = decode(0x2A5, bytes.fromhex("0000271000004E20"))
    >>> frame                                   # doctest: +ELLIPSIS
    JointFeedback(pair=0, q_a=0.17453..., q_b=0.34906...)
    >>> encode(frame) == (0x2A5, bytes.fromhex("0000271000004E20"))
    True

Rules:
* :func:`decode` never raises. An ID this protocol does not know gives :class:`UnknownFrame`; a
  frame too short for its layout, longer than 8 bytes, remote, extended-ID or error-flagged, or a
  command whose fields leave the domain piper_sdk's constructors enforce (enum members, speed
  0..100 %, gripper effort 0..5 N*m, MIT CRC, ...) gives :class:`InvalidFrame` with the reason.
  Both keep the raw bytes and re-encode to them.
* Feedback enums are decoded to their :class:`~enum.IntEnum` when known and kept as plain ints
  otherwise (newer firmware adds codes, e.g. mode_feed 0x06 for MIT on S-V1.8-8+).
* Round trips are bit-exact: ``encode(decode(id, data)) == (id, data)`` for every frame laid out
  as the tables say (8 bytes, reserved bytes zero: what the SDK and firmware send). Reserved
  bytes are ignored on decode (as the SDK does) and written as zero.
* Encoding a dataclass validates it: a value that does not fit its field (range, NaN, domain)
  raises :class:`ValueError` naming the field. Values are rounded to the nearest wire unit.

The frames and their units: :mod:`.frames`; the field machinery: :mod:`.wire`.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Iterable, Union

import can

from manisplat.drivers.piper.frames import *  # noqa: F401,F403  (every frame class, enum and unit helper)
from manisplat.drivers.piper.frames import __all__ as _FRAME_NAMES
from manisplat.drivers.piper.frames import FirmwareData, JointCtrl, EndPoseCtrl, JointMitCtrl
from manisplat.drivers.piper.frames import (ArmStatus, CollisionConfig, CollisionReply, DriverHighSpeed,
                                            DriverLowSpeed, EndPoseFeedback, EndVelAccConfig, EndVelAccReply,
                                            GripperCtrl, GripperFeedback, GripperTeachConfig, GripperTeachReply,
                                            JointConfig, JointEndVelAcc, JointFeedback, MasterSlaveConfig, ModeCtrl,
                                            MotionCtrl1, MotorEnable, MotorLimitsConfig, MotorLimitsReply,
                                            MotorMaxAccReply, MotorParamQuery, MoveCPoint, ParamQuery, SettingReply)
from manisplat.drivers.piper.wire import Field, Frame, InvalidFrame, LayoutFrame, UndocumentedFrame, UnknownFrame

# ----------------------------------------------------------------------------------------------
# registry, decode, encode

PiperFrame = Union[LayoutFrame, JointMitCtrl, FirmwareData]
AnyFrame = Union[PiperFrame, UnknownFrame, InvalidFrame, UndocumentedFrame]

#: every decodable frame class
FRAME_CLASSES: tuple[type, ...] = (
    ArmStatus, EndPoseFeedback, JointFeedback, GripperFeedback, DriverHighSpeed, DriverLowSpeed,
    SettingReply, MotorLimitsReply, MotorMaxAccReply, EndVelAccReply, CollisionReply, GripperTeachReply,
    JointEndVelAcc, MotionCtrl1, ModeCtrl, EndPoseCtrl, JointCtrl, MoveCPoint, GripperCtrl, MasterSlaveConfig,
    MotorEnable, MotorParamQuery, MotorLimitsConfig, JointConfig, ParamQuery, EndVelAccConfig, CollisionConfig,
    GripperTeachConfig, JointMitCtrl, FirmwareData,
)
UNDOCUMENTED_IDS = frozenset({0x121, 0x422})

#: CAN ID -> frame class
REGISTRY: dict[int, type] = {}
for _cls in FRAME_CLASSES:
    for _id in _cls.ids():
        assert _id not in REGISTRY, hex(_id)
        REGISTRY[_id] = _cls


def decode(can_id: int, data: bytes | bytearray, *, is_extended_id: bool = False, is_remote_frame: bool = False,
           is_error_frame: bool = False) -> AnyFrame:
    """The typed frame of one CAN frame; never raises (see the module docstring).

    Args:
        can_id: arbitration ID.
        data: payload, 0..8 bytes (more is invalid: classic CAN).
    """
    cls = REGISTRY.get(can_id)
    data = bytes(data)
    if is_error_frame:
        return InvalidFrame(can_id, data, "error frame")
    if cls is None:
        if can_id in UNDOCUMENTED_IDS and not (is_extended_id or is_remote_frame) and len(data) <= 8:
            return UndocumentedFrame(can_id, data)
        return UnknownFrame(can_id, data)
    if is_extended_id:
        return InvalidFrame(can_id, data, "extended (29-bit) ID; the PiPER uses 11-bit IDs")
    if is_remote_frame:
        return InvalidFrame(can_id, data, "remote frame")
    if len(data) > 8:
        return InvalidFrame(can_id, data, f"{len(data)} bytes: classic CAN carries at most 8")
    if len(data) < cls.SIZE:
        return InvalidFrame(can_id, data, f"{cls.__name__}: {len(data)} bytes, needs {cls.SIZE}")
    try:
        return cls.unpack(can_id, data)
    except Exception as exc:  # a bug here must not kill a reader thread: report it as invalid
        return InvalidFrame(can_id, data, f"{cls.__name__}: decoder error {exc!r}")


def decode_message(msg: can.Message) -> AnyFrame:
    """:func:`decode` of a python-can message."""
    return decode(msg.arbitration_id, msg.data, is_extended_id=msg.is_extended_id,
                  is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame)


def encode(frame: Frame) -> tuple[int, bytes]:
    """``(can_id, data)`` of ``frame``; ValueError when a field does not fit."""
    return frame.can_id, frame.pack()


def to_message(frame: Frame, timestamp: float = 0.0) -> can.Message:
    """A python-can message (11-bit ID) carrying ``frame``."""
    can_id, data = encode(frame)
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False, timestamp=timestamp)


def parse_candump(text: str) -> tuple[int, bytes]:
    """``(can_id, data)`` of a candump/cansend frame string such as ``"471#0702000000000000"``."""
    ident, _, payload = text.strip().partition("#")
    if not _:
        raise ValueError(f"{text!r}: expected ID#DATA")
    return int(ident, 16), bytes.fromhex(payload)


def joint_ctrl_frames(q: Iterable[float]) -> list[JointCtrl]:
    """The three 0x155..0x157 frames of a 6-joint target ``q`` (rad)."""
    q = [float(v) for v in q]
    if len(q) != 6:
        raise ValueError(f"joint target: expected 6 values, got {len(q)}")
    return [JointCtrl(p, q[2 * p], q[2 * p + 1]) for p in range(3)]


def end_pose_ctrl_frames(xyz: Iterable[float], rpy: Iterable[float]) -> list[EndPoseCtrl]:
    """The three 0x152..0x154 frames of a flange target: ``xyz`` m, ``rpy`` rad."""
    x, y, z = (float(v) for v in xyz)
    rx, ry, rz = (float(v) for v in rpy)
    return [EndPoseCtrl(0, x, y), EndPoseCtrl(1, z, rx), EndPoseCtrl(2, ry, rz)]


def field_names(cls: type) -> tuple[str, ...]:
    """The dataclass field names of a frame class, in order."""
    return tuple(f.name for f in fields(cls))


__all__ = [*_FRAME_NAMES, "AnyFrame", "FRAME_CLASSES", "Field", "Frame", "InvalidFrame", "LayoutFrame", "PiperFrame",
           "REGISTRY", "UNDOCUMENTED_IDS", "UndocumentedFrame", "UnknownFrame", "decode", "decode_message", "encode",
           "end_pose_ctrl_frames", "field_names", "joint_ctrl_frames", "parse_candump", "to_message"]
