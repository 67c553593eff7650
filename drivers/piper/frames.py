"""Every PiPER CAN frame as a frozen dataclass in SI units (reference ``piper_can.md`` §1.2-1.6).

Units and the choices where sources disagree:
* Joint angles, end-pose angles: 0.001 deg -> rad. Lengths: 0.001 mm -> m.
* Driver position (0x251..0x256): the SDK docs say both "rad" and "0.001 rad"; pyAgxArm decodes
  x1e-3, so 0.001 rad (unverified on hardware here; comparing with 0x2A5..0x2A7 would settle it).
* Driver current: the SDK message doc says uint16 but the parser (and pyAgxArm) read int16: int16.
* Max joint speed (0x473, 0x474): the SDK says 0.001 rad/s before firmware V1.5-8 and 0.01 rad/s
  from V1.5-8 on; this project targets S-V1.6-3+ (the built-in kinematics), so 0.01 rad/s.
* Gripper max range (0x47D/0x47E B1): mm per the SDK docstring (values 0, 70, 100) -> m.
* MIT (0x15A..0x15F): the table's V2 layout, p 16 bit in +-12.5 rad, v 12 bit +-45 rad/s,
  kp 12 bit 0..500, kd 12 bit -5..5, t 8 bit +-18 N*m, then a 4-bit XOR CRC of bytes 0..6. The
  SDK 0.6.x truncates (``int()``) when quantising, this module rounds, so an SDK frame and ours
  for the same float may differ by 1 LSB; decoding either is exact. Firmware S-V1.8-8+ (12-bit t,
  no CRC) is not decoded by this layout: 15 in 16 of its frames fail the CRC check and come out
  invalid, the rest decode with a wrong torque.
* 0x121 (light), 0x422 (upgrade silent mode): the tables give no layout; they decode to
  :class:`UndocumentedFrame` carrying the bytes.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar

from manisplat.drivers.piper.wire import (CENTI, DECI, DECIDEG, MDEG, MILLI, ONE, UM, Field, Frame, InvalidFrame,
                                          LayoutFrame)

__all__ = [
    "ArmStatus",
    "ArmStatusCode",
    "CanId",
    "CollisionConfig",
    "CollisionReply",
    "CtrlMode",
    "DriverHighSpeed",
    "DriverLowSpeed",
    "EFFORT_PER_AMP",
    "EStop",
    "EndPoseCtrl",
    "EndPoseFeedback",
    "EndVelAccConfig",
    "EndVelAccReply",
    "FirmwareData",
    "GripperCode",
    "GripperCtrl",
    "GripperFeedback",
    "GripperTeachConfig",
    "GripperTeachReply",
    "JointConfig",
    "JointCtrl",
    "JointEndVelAcc",
    "JointFeedback",
    "JointMitCtrl",
    "Linkage",
    "MIT_RANGES",
    "MasterSlaveConfig",
    "MitMode",
    "ModeCtrl",
    "MotionCtrl1",
    "MotorEnable",
    "MotorLimitsConfig",
    "MotorLimitsReply",
    "MotorMaxAccReply",
    "MotorParamQuery",
    "MoveCPoint",
    "MoveMode",
    "ParamQuery",
    "SettingReply",
    "mit_quantize",
    "mit_value",
]

#: piper_sdk's effort = current x coefficient (N*m per A) for joints 1-3 and 4-6
#: (``feedback/arm_feedback_high_spd.py``; firmware <= 1.8-2 reports J1-3 four times too low).
EFFORT_PER_AMP = (1.18125, 1.18125, 1.18125, 0.95844, 0.95844, 0.95844)

# ----------------------------------------------------------------------------------------------
# enums (reference §1.3, §1.5)


class CtrlMode(IntEnum):
    """Control mode (0x2A1 B0 feedback, 0x151 B0 command)."""

    STANDBY = 0x00
    CAN = 0x01
    TEACHING = 0x02
    ETHERNET = 0x03
    WIFI = 0x04
    REMOTE = 0x05
    LINKAGE_TEACHING = 0x06
    OFFLINE_TRAJECTORY = 0x07


class ArmStatusCode(IntEnum):
    """Arm status (0x2A1 B1)."""

    NORMAL = 0x00
    EMERGENCY_STOP = 0x01
    NO_SOLUTION = 0x02
    SINGULARITY = 0x03
    TARGET_BEYOND_LIMIT = 0x04
    JOINT_COMM_ERROR = 0x05
    BRAKE_NOT_RELEASED = 0x06
    COLLISION = 0x07
    DRAG_TEACH_OVERSPEED = 0x08
    JOINT_STATUS_ERROR = 0x09
    OTHER = 0x0A
    TEACH_RECORD = 0x0B
    TEACH_EXECUTE = 0x0C
    TEACH_PAUSE = 0x0D
    MAINBOARD_OVERTEMP = 0x0E
    BRAKE_RESISTOR_OVERTEMP = 0x0F


class MoveMode(IntEnum):
    """Motion mode (0x151 B1 command, 0x2A1 B2 feedback)."""

    P = 0x00
    J = 0x01
    L = 0x02
    C = 0x03
    M = 0x04
    CPV = 0x05
    M_V188 = 0x06  # MIT on firmware S-V1.8-8+ (feedback only)


class MitMode(IntEnum):
    """0x151 B3: 0x00 position-velocity, 0xAD MIT / "JS" fast follow, 0xFF invalid."""

    POSITION_VELOCITY = 0x00
    MIT = 0xAD
    INVALID = 0xFF


class EStop(IntEnum):
    """0x150 B0."""

    NONE = 0x00
    STOP = 0x01  # the arm sinks slowly, damped
    RESUME = 0x02  # = ResetPiper: cuts motor power (the arm drops), clears errors


class GripperCode(IntEnum):
    """0x159 B6."""

    DISABLE = 0x00
    ENABLE = 0x01
    DISABLE_CLEAR_ERROR = 0x02
    ENABLE_CLEAR_ERROR = 0x03


class Linkage(IntEnum):
    """0x470 B0."""

    NONE = 0x00
    TEACH_INPUT = 0xFA  # master / leader
    MOTION_OUTPUT = 0xFC  # slave / follower


class CanId(IntEnum):
    """First CAN ID of every frame family (families span consecutive IDs)."""

    ARM_STATUS = 0x2A1
    END_POSE = 0x2A2  # ..0x2A4
    JOINT_FEEDBACK = 0x2A5  # ..0x2A7
    GRIPPER_FEEDBACK = 0x2A8
    DRIVER_HIGH_SPEED = 0x251  # ..0x256
    DRIVER_LOW_SPEED = 0x261  # ..0x266
    MOTION_CTRL_1 = 0x150
    MODE_CTRL = 0x151
    END_POSE_CTRL = 0x152  # ..0x154
    JOINT_CTRL = 0x155  # ..0x157
    MOVE_C_POINT = 0x158
    GRIPPER_CTRL = 0x159
    JOINT_MIT_CTRL = 0x15A  # ..0x15F
    LIGHT_CTRL = 0x121
    MASTER_SLAVE_CONFIG = 0x470
    MOTOR_ENABLE = 0x471
    MOTOR_PARAM_QUERY = 0x472
    MOTOR_LIMITS_REPLY = 0x473
    MOTOR_LIMITS_CONFIG = 0x474
    JOINT_CONFIG = 0x475
    SETTING_REPLY = 0x476
    PARAM_QUERY = 0x477
    END_VEL_ACC_REPLY = 0x478
    END_VEL_ACC_CONFIG = 0x479
    COLLISION_CONFIG = 0x47A
    COLLISION_REPLY = 0x47B
    MOTOR_MAX_ACC_REPLY = 0x47C
    GRIPPER_TEACH_CONFIG = 0x47D
    GRIPPER_TEACH_REPLY = 0x47E
    JOINT_END_VEL_ACC = 0x481  # ..0x486
    UPGRADE_SILENT_MODE = 0x422
    FIRMWARE = 0x4AF


def _values(*enums: type[IntEnum]) -> frozenset[int]:
    return frozenset(int(m) for e in enums for m in e)


_MOTOR_1_6 = frozenset(range(1, 7))
_MOTOR_ALL = frozenset(range(1, 8)) | {0xFF}
_AE = (0x00, 0xAE)



# -- feedback, arm -> host ----------------------------------------------------------------------


@dataclass(frozen=True)
class ArmStatus(LayoutFrame):
    """0x2A1 arm status, 200 Hz. ``err_code`` bits 0-5: joint 1-6 communication error,
    bits 8-13: joint 1-6 angle limit exceeded."""

    ctrl_mode: CtrlMode | int
    arm_status: ArmStatusCode | int
    mode_feed: MoveMode | int
    teach_status: int
    motion_status: int  # 0 reached the target, 1 not yet
    trajectory_num: int
    err_code: int

    BASE_ID = 0x2A1
    FIELDS = (Field("ctrl_mode", "B", enum=CtrlMode), Field("arm_status", "B", enum=ArmStatusCode),
              Field("mode_feed", "B", enum=MoveMode), Field("teach_status", "B"), Field("motion_status", "B"),
              Field("trajectory_num", "B"), Field("err_code", "H"))

    @property
    def joint_comm_errors(self) -> tuple[bool, ...]:
        return tuple(bool(self.err_code >> i & 1) for i in range(6))

    @property
    def joint_limit_errors(self) -> tuple[bool, ...]:
        return tuple(bool(self.err_code >> (8 + i) & 1) for i in range(6))


@dataclass(frozen=True)
class EndPoseFeedback(LayoutFrame):
    """0x2A2..0x2A4 flange pose, one pair of values per frame (SDK FK convention, roll-pitch-yaw).

    part 0 (0x2A2): a = x, b = y (m); part 1 (0x2A3): a = z (m), b = rx (rad);
    part 2 (0x2A4): a = ry, b = rz (rad).
    """

    part: int
    a: float
    b: float

    BASE_ID = 0x2A2
    INDEX = ("part", 0, 3)
    FIELDS = (Field("a", "i", UM), Field("b", "i", UM))  # scales fixed per part below

    def pack(self) -> bytes:
        return _pose_pack(self.part, self.a, self.b)

    @classmethod
    def unpack(cls, can_id: int, data: bytes) -> Frame:
        return _pose_unpack(cls, can_id, data)


@dataclass(frozen=True)
class JointFeedback(LayoutFrame):
    """0x2A5..0x2A7 joint angles (rad): pair 0 = (J1, J2), 1 = (J3, J4), 2 = (J5, J6).
    A full joint vector takes three frames (see ``manisplat.drivers.piper.assembler``)."""

    pair: int
    q_a: float
    q_b: float

    BASE_ID = 0x2A5
    INDEX = ("pair", 0, 3)
    FIELDS = (Field("q_a", "i", MDEG), Field("q_b", "i", MDEG))

    @property
    def joints(self) -> tuple[int, int]:
        """The 1-based joint numbers of ``q_a``, ``q_b``."""
        return 2 * self.pair + 1, 2 * self.pair + 2


@dataclass(frozen=True)
class GripperFeedback(LayoutFrame):
    """0x2A8 gripper: opening ``width`` (m), ``effort`` (N*m), ``status`` bits (0 low voltage,
    1 motor over-temp, 2 over-current, 3 driver over-temp, 4 sensor fault, 5 driver error,
    6 driver enabled, 7 zeroed)."""

    width: float
    effort: float
    status: int

    BASE_ID = 0x2A8
    FIELDS = (Field("width", "i", UM), Field("effort", "h", MILLI), Field("status", "B"))

    @property
    def enabled(self) -> bool:
        return bool(self.status >> 6 & 1)


@dataclass(frozen=True)
class DriverHighSpeed(LayoutFrame):
    """0x251..0x256 motor driver, 200 Hz: ``speed`` rad/s, ``current`` A, ``position`` rad."""

    motor: int
    speed: float
    current: float
    position: float

    BASE_ID = 0x251
    INDEX = ("motor", 1, 6)
    FIELDS = (Field("speed", "h", MILLI), Field("current", "h", MILLI), Field("position", "i", MILLI))

    @property
    def effort(self) -> float:
        """Joint torque (N*m) as piper_sdk computes it: current x per-joint coefficient."""
        return self.current * EFFORT_PER_AMP[self.motor - 1]


@dataclass(frozen=True)
class DriverLowSpeed(LayoutFrame):
    """0x261..0x266 motor driver, 40 Hz: bus ``voltage`` V, temperatures degC, ``status`` bits
    (0 low voltage, 1 motor over-temp, 2 over-current, 3 driver over-temp, 4 collision,
    5 driver error, 6 driver enabled, 7 stall), ``bus_current`` A."""

    motor: int
    voltage: float
    driver_temp: float
    motor_temp: float
    status: int
    bus_current: float

    BASE_ID = 0x261
    INDEX = ("motor", 1, 6)
    FIELDS = (Field("voltage", "H", DECI), Field("driver_temp", "h", ONE), Field("motor_temp", "b", ONE),
              Field("status", "B"), Field("bus_current", "H", MILLI))

    @property
    def enabled(self) -> bool:
        return bool(self.status >> 6 & 1)


@dataclass(frozen=True)
class SettingReply(LayoutFrame):
    """0x476 reply to a setting command (also sent by a host as "instruction response
    config"): ``instruction_index`` (low byte of the command ID answered), ``zero_set_ok``."""

    instruction_index: int
    zero_set_ok: int

    BASE_ID = 0x476
    FIELDS = (Field("instruction_index", "B"), Field("zero_set_ok", "B"))


@dataclass(frozen=True)
class MotorLimitsReply(LayoutFrame):
    """0x473 reply to 0x472 content 1: angle limits (rad) and max speed (rad/s, 0.01 units)."""

    motor: int
    max_angle: float | None
    min_angle: float | None
    max_speed: float | None

    BASE_ID = 0x473
    FIELDS = (Field("motor", "B"), Field("max_angle", "h", DECIDEG, none_raw=0x7FFF),
              Field("min_angle", "h", DECIDEG, none_raw=0x7FFF), Field("max_speed", "H", CENTI, none_raw=0x7FFF))


@dataclass(frozen=True)
class MotorMaxAccReply(LayoutFrame):
    """0x47C reply to 0x472 content 2: max joint acceleration (rad/s^2)."""

    motor: int
    max_acc: float | None

    BASE_ID = 0x47C
    FIELDS = (Field("motor", "B"), Field("max_acc", "H", CENTI, none_raw=0x7FFF))


@dataclass(frozen=True)
class EndVelAccReply(LayoutFrame):
    """0x478 end-effector limits: m/s, rad/s, m/s^2, rad/s^2."""

    linear_vel: float | None
    angular_vel: float | None
    linear_acc: float | None
    angular_acc: float | None

    BASE_ID = 0x478
    FIELDS = tuple(Field(n, "H", MILLI, none_raw=0x7FFF)
                   for n in ("linear_vel", "angular_vel", "linear_acc", "angular_acc"))


@dataclass(frozen=True)
class CollisionReply(LayoutFrame):
    """0x47B collision protection level of joints 1..6 (0 off, 1..8)."""

    levels: tuple[int, int, int, int, int, int]

    BASE_ID = 0x47B
    FIELDS = tuple(Field(f"level{i}", "B") for i in range(1, 7))

    def pack(self) -> bytes:
        return _levels_pack(self)

    @classmethod
    def unpack(cls, can_id: int, data: bytes) -> Frame:
        return _levels_unpack(cls, can_id, data)


@dataclass(frozen=True)
class GripperTeachReply(LayoutFrame):
    """0x47E gripper / teach-pendant parameters: stroke coefficient %, max range (m), friction."""

    teach_range_pct: int
    max_range: float
    friction: int

    BASE_ID = 0x47E
    FIELDS = (Field("teach_range_pct", "B"), Field("max_range", "B", MILLI), Field("friction", "B"))


@dataclass(frozen=True)
class JointEndVelAcc(LayoutFrame):
    """0x481..0x486 (only when enabled by 0x477 B2): end-effector m/s, rad/s, m/s^2, rad/s^2."""

    motor: int
    linear_vel: float
    angular_vel: float
    linear_acc: float
    angular_acc: float

    BASE_ID = 0x481
    INDEX = ("motor", 1, 6)
    FIELDS = tuple(Field(n, "H", MILLI) for n in ("linear_vel", "angular_vel", "linear_acc", "angular_acc"))


# -- commands, host -> arm ----------------------------------------------------------------------


@dataclass(frozen=True)
class MotionCtrl1(LayoutFrame):
    """0x150: e-stop (1) / resume = reset (2, cuts motor power: the arm drops), trajectory and
    drag-teach operations."""

    emergency_stop: EStop | int = EStop.NONE
    track_ctrl: int = 0
    drag_teach: int = 0

    BASE_ID = 0x150
    COMMAND = True
    FIELDS = (Field("emergency_stop", "B", enum=EStop, domain=_values(EStop)),
              Field("track_ctrl", "B", domain=frozenset(range(9))), Field("drag_teach", "B", domain=frozenset(range(8))))


@dataclass(frozen=True)
class ModeCtrl(LayoutFrame):
    """0x151: control mode, move mode, speed % (0..100), MIT flag, residence time, installation."""

    ctrl_mode: CtrlMode | int = CtrlMode.CAN
    move_mode: MoveMode | int = MoveMode.J
    speed_pct: int = 50
    mit_mode: MitMode | int = MitMode.POSITION_VELOCITY
    residence_time: int = 0
    installation: int = 0  # 0 n/a, 1 upright, 2 left side, 3 right side

    BASE_ID = 0x151
    COMMAND = True
    FIELDS = (Field("ctrl_mode", "B", enum=CtrlMode, domain=frozenset({0x00, 0x01, 0x03, 0x04, 0x07})),
              Field("move_mode", "B", enum=MoveMode, domain=frozenset(range(6))),
              Field("speed_pct", "B", domain=frozenset(range(101))),
              Field("mit_mode", "B", enum=MitMode, domain=_values(MitMode)),
              Field("residence_time", "B"), Field("installation", "B", domain=frozenset(range(4))))


@dataclass(frozen=True)
class EndPoseCtrl(LayoutFrame):
    """0x152..0x154 end-pose target, same parts and units as :class:`EndPoseFeedback`."""

    part: int
    a: float
    b: float

    BASE_ID = 0x152
    INDEX = ("part", 0, 3)
    COMMAND = True
    FIELDS = EndPoseFeedback.FIELDS

    def pack(self) -> bytes:
        return _pose_pack(self.part, self.a, self.b)

    @classmethod
    def unpack(cls, can_id: int, data: bytes) -> Frame:
        return _pose_unpack(cls, can_id, data)


@dataclass(frozen=True)
class JointCtrl(LayoutFrame):
    """0x155..0x157 joint targets (rad), pairs as :class:`JointFeedback`. Also sent by a
    teach-input (master) arm."""

    pair: int
    q_a: float
    q_b: float

    BASE_ID = 0x155
    INDEX = ("pair", 0, 3)
    COMMAND = True
    FIELDS = JointFeedback.FIELDS


@dataclass(frozen=True)
class MoveCPoint(LayoutFrame):
    """0x158 MOVE C point index: 1 start, 2 middle, 3 end."""

    index: int

    BASE_ID = 0x158
    COMMAND = True
    FIELDS = (Field("index", "B", domain=frozenset(range(4))),)


@dataclass(frozen=True)
class GripperCtrl(LayoutFrame):
    """0x159 gripper target: ``width`` m, ``effort`` N*m (0..5), ``code`` (enable/disable,
    clear error), ``set_zero`` (True = 0xAE: take the current position as zero)."""

    width: float
    effort: float = 1.0
    code: GripperCode | int = GripperCode.ENABLE
    set_zero: bool = False

    BASE_ID = 0x159
    COMMAND = True
    FIELDS = (Field("width", "i", UM), Field("effort", "H", MILLI, domain=frozenset(range(5001))),
              Field("code", "B", enum=GripperCode, domain=_values(GripperCode)), Field("set_zero", "B", flag=_AE))


@dataclass(frozen=True)
class MasterSlaveConfig(LayoutFrame):
    """0x470: linkage role, feedback ID offset (0x2Ax -> +0x10/+0x20), control ID offset
    (0x15x -> +0x10/+0x20), linkage target offset."""

    linkage: Linkage | int
    feedback_offset: int = 0
    ctrl_offset: int = 0
    linkage_offset: int = 0

    BASE_ID = 0x470
    COMMAND = True
    _OFF = frozenset({0x00, 0x10, 0x20})
    FIELDS = (Field("linkage", "B", enum=Linkage, domain=_values(Linkage)), Field("feedback_offset", "B", domain=_OFF),
              Field("ctrl_offset", "B", domain=_OFF), Field("linkage_offset", "B", domain=_OFF))


@dataclass(frozen=True)
class MotorEnable(LayoutFrame):
    """0x471 enable (B1 0x02) or disable (B1 0x01) motor 1..6, or all (7 or 0xFF).
    Disabling unpowers the motors at once: an unsupported arm falls."""

    motor: int
    enable: bool

    BASE_ID = 0x471
    COMMAND = True
    FIELDS = (Field("motor", "B", domain=_MOTOR_ALL), Field("enable", "B", flag=(0x01, 0x02)))


@dataclass(frozen=True)
class MotorParamQuery(LayoutFrame):
    """0x472 query of motor 1..6: content 1 angle limits / max speed (reply 0x473),
    2 max acceleration (reply 0x47C)."""

    motor: int
    content: int

    BASE_ID = 0x472
    COMMAND = True
    FIELDS = (Field("motor", "B", domain=_MOTOR_1_6), Field("content", "B", domain=frozenset({1, 2})))


@dataclass(frozen=True)
class MotorLimitsConfig(LayoutFrame):
    """0x474 set angle limits (rad) and max speed (rad/s) of motor 1..6; None leaves one as is
    (0x7FFF)."""

    motor: int
    max_angle: float | None = None
    min_angle: float | None = None
    max_speed: float | None = None

    BASE_ID = 0x474
    COMMAND = True
    FIELDS = (Field("motor", "B", domain=_MOTOR_1_6), Field("max_angle", "h", DECIDEG, none_raw=0x7FFF),
              Field("min_angle", "h", DECIDEG, none_raw=0x7FFF),
              Field("max_speed", "H", CENTI, none_raw=0x7FFF, domain=frozenset(range(301)) | {0x7FFF}))


@dataclass(frozen=True)
class JointConfig(LayoutFrame):
    """0x475 joint settings of motor 1..7: set zero, apply ``max_acc`` (rad/s^2, 0..5),
    clear the joint error."""

    motor: int
    set_zero: bool = False
    apply_acc: bool = False
    max_acc: float | None = None
    clear_error: bool = False

    BASE_ID = 0x475
    COMMAND = True
    FIELDS = (Field("motor", "B", domain=frozenset(range(1, 8))), Field("set_zero", "B", flag=_AE),
              Field("apply_acc", "B", flag=_AE),
              Field("max_acc", "H", CENTI, none_raw=0x7FFF, domain=frozenset(range(501)) | {0x7FFF}),
              Field("clear_error", "B", flag=_AE))


@dataclass(frozen=True)
class ParamQuery(LayoutFrame):
    """0x477 parameter query/set: ``query`` 1 end vel/acc (-> 0x478), 2 collision levels
    (-> 0x47B), 3 trajectory index, 4 gripper/teach params (-> 0x47E); ``setting`` 1 end
    vel/acc defaults, 2 all joint limits defaults; ``feedback_48x`` 1 off / 2 on;
    ``load_valid`` (0xAE) and ``load`` 0 none, 1 half, 2 full, 3 invalid."""

    query: int = 0
    setting: int = 0
    feedback_48x: int = 0
    load_valid: bool = False
    load: int = 3

    BASE_ID = 0x477
    COMMAND = True
    FIELDS = (Field("query", "B", domain=frozenset(range(5))), Field("setting", "B", domain=frozenset(range(3))),
              Field("feedback_48x", "B", domain=frozenset(range(3))), Field("load_valid", "B", flag=_AE),
              Field("load", "B", domain=frozenset(range(4))))


@dataclass(frozen=True)
class EndVelAccConfig(LayoutFrame):
    """0x479 set end-effector limits (units of :class:`EndVelAccReply`; None = 0x7FFF)."""

    linear_vel: float | None = None
    angular_vel: float | None = None
    linear_acc: float | None = None
    angular_acc: float | None = None

    BASE_ID = 0x479
    COMMAND = True
    FIELDS = EndVelAccReply.FIELDS


@dataclass(frozen=True)
class CollisionConfig(LayoutFrame):
    """0x47A set the collision protection level (0..8) of joints 1..6."""

    levels: tuple[int, int, int, int, int, int]

    BASE_ID = 0x47A
    COMMAND = True
    FIELDS = tuple(Field(f"level{i}", "B", domain=frozenset(range(9))) for i in range(1, 7))

    def pack(self) -> bytes:
        return _levels_pack(self)

    @classmethod
    def unpack(cls, can_id: int, data: bytes) -> Frame:
        return _levels_unpack(cls, can_id, data)


@dataclass(frozen=True)
class GripperTeachConfig(LayoutFrame):
    """0x47D set gripper / teach-pendant parameters: stroke coefficient 100..200 %, max range
    0 / 0.07 / 0.1 m, friction 1..10."""

    teach_range_pct: int = 100
    max_range: float = 0.0
    friction: int = 1

    BASE_ID = 0x47D
    COMMAND = True
    FIELDS = (Field("teach_range_pct", "B", domain=frozenset(range(100, 201))),
              Field("max_range", "B", MILLI, domain=frozenset({0, 70, 100})),
              Field("friction", "B", domain=frozenset(range(1, 11))))


# -- special layouts -----------------------------------------------------------------------------

MIT_RANGES = {"position": (-12.5, 12.5, 16), "velocity": (-45.0, 45.0, 12), "kp": (0.0, 500.0, 12),
              "kd": (-5.0, 5.0, 12), "torque": (-18.0, 18.0, 8)}


def mit_quantize(name: str, value: float) -> int:
    """Raw unsigned code of MIT field ``name`` (rounded; ValueError outside its range)."""
    lo, hi, bits = MIT_RANGES[name]
    x = float(value)
    if not (math.isfinite(x) and lo <= x <= hi):
        raise ValueError(f"JointMitCtrl.{name}: {value!r} outside [{lo}, {hi}]")
    return round((x - lo) * ((1 << bits) - 1) / (hi - lo))


def mit_value(name: str, raw: int) -> float:
    """Float of MIT field ``name`` from its raw code."""
    lo, hi, bits = MIT_RANGES[name]
    return lo + raw * (hi - lo) / ((1 << bits) - 1)


@dataclass(frozen=True)
class JointMitCtrl(Frame):
    """0x15A..0x15F MIT command of motor 1..6: position rad, velocity rad/s, gains kp, kd,
    feed-forward torque N*m. Values are quantised to the wire grid (see module docstring)."""

    motor: int
    position: float
    velocity: float = 0.0
    kp: float = 10.0
    kd: float = 0.8
    torque: float = 0.0

    BASE_ID: ClassVar[int] = 0x15A
    COMMAND: ClassVar[bool] = True
    SIZE: ClassVar[int] = 8

    @classmethod
    def ids(cls) -> range:
        return range(0x15A, 0x160)

    def __post_init__(self) -> None:
        self.pack()

    @property
    def can_id(self) -> int:
        if isinstance(self.motor, bool) or not isinstance(self.motor, int) or not 1 <= self.motor <= 6:
            raise ValueError(f"JointMitCtrl.motor: {self.motor!r} not in 1..6")
        return 0x159 + self.motor

    def pack(self) -> bytes:
        self.can_id  # noqa: B018
        p, v, kp, kd, t = (mit_quantize(n, getattr(self, n)) for n in MIT_RANGES)
        head = bytes([p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | kp >> 8, kp & 0xFF, kd >> 4,
                      (kd & 0xF) << 4 | t >> 4])
        crc = 0
        for byte in head:
            crc ^= byte
        return head + bytes([(t & 0xF) << 4 | (crc & 0xF)])

    @classmethod
    def unpack(cls, can_id: int, data: bytes) -> Frame:
        d = data
        crc = d[0] ^ d[1] ^ d[2] ^ d[3] ^ d[4] ^ d[5] ^ d[6]
        if crc & 0xF != d[7] & 0xF:
            return InvalidFrame(can_id, bytes(data), f"JointMitCtrl: CRC {d[7] & 0xF:X} != {crc & 0xF:X}")
        raw = {"position": d[0] << 8 | d[1], "velocity": d[2] << 4 | d[3] >> 4, "kp": (d[3] & 0xF) << 8 | d[4],
               "kd": d[5] << 4 | d[6] >> 4, "torque": (d[6] & 0xF) << 4 | d[7] >> 4}
        frame = object.__new__(cls)
        frame.__dict__.update(motor=can_id - 0x159, **{n: mit_value(n, r) for n, r in raw.items()})
        return frame


@dataclass(frozen=True)
class FirmwareData(Frame):
    """0x4AF: a host's firmware read request, or one chunk of the arm's ASCII version string
    (both directions use the ID; the SDK concatenates the chunks)."""

    data: bytes = bytes(8)

    BASE_ID: ClassVar[int] = 0x4AF
    COMMAND: ClassVar[bool] = False
    SIZE: ClassVar[int] = 0

    @classmethod
    def ids(cls) -> range:
        return range(0x4AF, 0x4B0)

    def __post_init__(self) -> None:
        if len(self.data) > 8:
            raise ValueError(f"FirmwareData.data: {len(self.data)} bytes, at most 8")

    @property
    def can_id(self) -> int:
        return 0x4AF

    def pack(self) -> bytes:
        return bytes(self.data)

    @classmethod
    def unpack(cls, can_id: int, data: bytes) -> Frame:
        return cls(bytes(data))


# -- helpers shared by a few classes -------------------------------------------------------------

_POSE_SCALES = ((UM, UM), (UM, MDEG), (MDEG, MDEG))


def _pose_pack(part: int, a: float, b: float) -> bytes:
    if isinstance(part, bool) or part not in (0, 1, 2):
        raise ValueError(f"end pose part: {part!r} not in 0..2")
    sa, sb = _POSE_SCALES[part]
    return struct.pack(">ii", Field("a", "i", sa).to_raw(a), Field("b", "i", sb).to_raw(b))


def _pose_unpack(cls: type, can_id: int, data: bytes) -> Frame:
    part = can_id - cls.BASE_ID
    ra, rb = struct.unpack_from(">ii", data)
    sa, sb = _POSE_SCALES[part]
    frame = object.__new__(cls)
    frame.__dict__.update(part=part, a=ra / sa[0] * sa[1], b=rb / sb[0] * sb[1])
    return frame


def _levels_pack(frame: Any) -> bytes:
    levels = tuple(frame.levels)
    if len(levels) != 6:
        raise ValueError(f"{type(frame).__name__}.levels: expected 6 values, got {len(levels)}")
    return bytes(f.to_raw(v) for f, v in zip(frame.FIELDS, levels)).ljust(8, b"\0")


def _levels_unpack(cls: type, can_id: int, data: bytes) -> Frame:
    try:
        levels = tuple(f.to_value(r) for f, r in zip(cls.FIELDS, data[:6]))
    except ValueError as exc:
        return InvalidFrame(can_id, bytes(data), f"{cls.__name__}: {exc}")
    frame = object.__new__(cls)
    frame.__dict__.update(levels=levels)
    return frame
