"""The simulated PiPER's firmware, as a pure state machine: frames in, state stepped by ``dt``,
feedback frames out. :class:`~.simulated.SimulatedPiper` puts it on a bus with a clock.

Behaviour (what the protocol tables say, and this model's simplifications):
* Commands are decoded with :mod:`.protocol`, so any correct host works (the SDK's exact bytes
  included). Invalid and unknown frames are counted and ignored.
* Joints follow their target only when all six motors are enabled (0x471), the control mode is
  CAN (0x151 B0=1), the move mode is J (0x151 B1=1) and there is no e-stop. Each joint moves as
  a first-order lag (time constant ``tau_s``; "JS" mode, MIT flag 0xAD, uses ``tau_s / 4``),
  its speed capped at the robot's velocity limit x speed % (0x151 B2). A target outside the joint
  limits is refused as a whole (status 4, "target beyond limit"); the previous one is kept.
* On enable, and when the control mode becomes CAN, the target is reset to the current position,
  so a stale target never makes the arm jump.
* MOVE M (MIT, 0x15A..0x15F): the position reference becomes the joint target (gains and torque
  are not simulated). MOVE P/L/C (Cartesian targets): not simulated; the arm stays put and a
  warning is logged once.
* E-stop (0x150 B0=1): status 1, motion stops and the arm holds (no gravity: the real arm sinks
  slowly); commands are ignored until reset. Reset (0x150 B0=2): errors cleared, motors unpowered,
  control mode standby, gripper disabled. Disable (0x471 B1=1): motors unpowered; with no gravity
  model the joints stay where they are.
* Gripper (0x159): code 1/3 enables it and sets the width target (lag + 0.1 m/s cap), 0/2
  disables it. Effort feedback is the commanded effort while enabled.
* Queries are answered: 0x472 -> 0x473 / 0x47C, 0x477 -> 0x478 / 0x47B / 0x47E, 0x4AF -> the
  firmware string; settings 0x474, 0x475, 0x479, 0x47A, 0x47D are applied and acknowledged with
  0x476.
* Playback: :meth:`PiperModel.play` replaces the joint dynamics by a recorded trajectory
  (linear interpolation in time, held at its end).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch

from manisplat.drivers.piper import protocol as P
from manisplat.geometry import matrix_to_rpy
from manisplat.robot import RobotModel, builtin_piper
from manisplat.robot.piper import dh_origin

log = logging.getLogger(__name__)

FEEDBACK_RATE_HZ = 200.0
LOW_SPEED_DIVIDER = 5  # 0x261..0x266 at 200 / 5 = 40 Hz
FIRMWARE = b"S-V1.6-3 SIM"


@dataclass
class SimConfig:
    """Settings of the simulated arm.

    Attributes:
        tau_s: first-order lag time constant of joints and gripper, s.
        gripper_speed: gripper speed cap, m/s.
        reached_tol: |target - q| below which a joint counts as arrived (status B4), rad.
        q0: (6,) initial joint angles, rad (default: zeros clipped into the limits).
        gripper0: initial gripper width, m.
        voltage: bus voltage reported by 0x26x, V.
        temperature: driver and motor temperature reported, degC.
        firmware: the version string answered to 0x4AF, ASCII.
    """

    tau_s: float = 0.05
    gripper_speed: float = 0.1
    reached_tol: float = 1e-3
    q0: np.ndarray | None = None
    gripper0: float = 0.0
    voltage: float = 24.0
    temperature: float = 30.0
    firmware: bytes = FIRMWARE


@dataclass
class Playback:
    """A recorded trajectory played as the arm's state: ``t`` (N,) s from its start, ``q`` (N, 6)
    rad, ``gripper`` (N,) m."""

    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
    start: float = 0.0  # model time when it began

    def at(self, now: float) -> tuple[np.ndarray, float]:
        s = now - self.start
        q = np.array([np.interp(s, self.t, self.q[:, j]) for j in range(6)])
        return q, float(np.interp(s, self.t, self.gripper))


class PiperModel:
    """The state machine. ``handle(frame)`` applies a decoded command and returns the replies;
    ``step(dt)`` advances the dynamics; ``feedback()`` gives one cycle of feedback frames.

    Attributes (state, SI units): ``q``, ``qd``, ``target`` (6,) rad, rad/s; ``enabled`` (6,)
    bool; ``ctrl_mode``, ``move_mode``, ``mit_mode``, ``speed_pct``; ``estop``; ``arm_status``;
    ``gripper``, ``gripper_target`` m; ``gripper_enabled``; ``time`` s; ``counts`` of handled,
    ignored and invalid frames.
    """

    def __init__(self, robot: RobotModel | None = None, config: SimConfig | None = None) -> None:
        self.robot = robot if robot is not None else builtin_piper(with_geometry=False)
        self.config = config if config is not None else SimConfig()
        self.lower = self.robot.lower.copy()
        self.upper = self.robot.upper.copy()
        self.vmax = self.robot.velocity_limits.copy()
        self.amax = self.robot.acceleration_limits.copy()
        q0 = np.zeros(6) if self.config.q0 is None else np.asarray(self.config.q0, dtype=np.float64)
        self.q = np.clip(q0, self.lower, self.upper)
        self.qd = np.zeros(6)
        self.target = self.q.copy()
        self.enabled = np.zeros(6, dtype=bool)
        self.ctrl_mode = int(P.CtrlMode.STANDBY)
        self.move_mode = int(P.MoveMode.P)
        self.mit_mode = int(P.MitMode.POSITION_VELOCITY)
        self.speed_pct = 0
        self.estop = False
        self.arm_status = int(P.ArmStatusCode.NORMAL)
        self.gripper = float(self.config.gripper0)
        self.gripper_target = self.gripper
        self.gripper_effort = 0.0
        self.gripper_enabled = False
        self.collision_levels = (0,) * 6
        self.end_limits = (1.0, 1.0, 1.0, 1.0)  # m/s, rad/s, m/s^2, rad/s^2
        self.time = 0.0
        self.playback: Playback | None = None
        self.counts = {"handled": 0, "ignored": 0, "invalid": 0, "unknown": 0}
        self._warned: set[str] = set()
        self._origins = [dh_origin(i) for i in range(6)]
        self._tick = 0

    # -- commands -------------------------------------------------------------------------------

    @property
    def following(self) -> bool:
        """Whether joint targets are being followed (enabled, CAN control, MOVE J or M, no e-stop)."""
        return (bool(self.enabled.all()) and self.ctrl_mode == P.CtrlMode.CAN and not self.estop
                and self.move_mode in (P.MoveMode.J, P.MoveMode.M))

    def handle(self, frame: P.AnyFrame) -> list[P.Frame]:
        """Apply one decoded frame; returns the frames the arm answers with."""
        kind = type(frame)
        if kind is P.InvalidFrame:
            self.counts["invalid"] += 1
            return []
        if kind is P.UnknownFrame:
            self.counts["unknown"] += 1
            return []
        if not (getattr(frame, "COMMAND", False) or kind is P.FirmwareData):
            self.counts["ignored"] += 1  # feedback IDs (another arm), 0x476 from a host, 0x121, 0x422
            return []
        if self.estop and not (kind is P.MotionCtrl1 and frame.emergency_stop == P.EStop.RESUME):
            self.counts["ignored"] += 1
            return []
        self.counts["handled"] += 1
        handler = getattr(self, f"_on_{kind.__name__}", None)
        if handler is None:
            self._warn_once(kind.__name__, f"simulated PiPER: {kind.__name__} is not simulated; ignored")
            return []
        return handler(frame) or []

    def _on_MotionCtrl1(self, f: P.MotionCtrl1) -> None:
        if f.emergency_stop == P.EStop.STOP:
            self.estop = True
            self.arm_status = int(P.ArmStatusCode.EMERGENCY_STOP)
            self.qd[:] = 0.0
            self.target = self.q.copy()
        elif f.emergency_stop == P.EStop.RESUME:
            self.estop = False
            self.arm_status = int(P.ArmStatusCode.NORMAL)
            self.enabled[:] = False
            self.gripper_enabled = False
            self.ctrl_mode = int(P.CtrlMode.STANDBY)
            self.qd[:] = 0.0
            self.target = self.q.copy()

    def _on_ModeCtrl(self, f: P.ModeCtrl) -> None:
        if f.ctrl_mode == P.CtrlMode.CAN and self.ctrl_mode != P.CtrlMode.CAN:
            self.target = self.q.copy()
        self.ctrl_mode, self.move_mode, self.mit_mode = int(f.ctrl_mode), int(f.move_mode), int(f.mit_mode)
        self.speed_pct = f.speed_pct
        if self.move_mode in (P.MoveMode.P, P.MoveMode.L, P.MoveMode.C, P.MoveMode.CPV):
            self._warn_once("cartesian", "simulated PiPER: MOVE P/L/C/CPV are not simulated; the arm stays put")

    def _on_JointCtrl(self, f: P.JointCtrl) -> None:
        self._set_targets([2 * f.pair, 2 * f.pair + 1], [f.q_a, f.q_b])

    def _on_JointMitCtrl(self, f: P.JointMitCtrl) -> None:
        if self.move_mode == P.MoveMode.M:
            self._set_targets([f.motor - 1], [f.position])

    def _set_targets(self, joints: list[int], values: list[float]) -> None:
        v = np.asarray(values)
        if np.any(v < self.lower[joints] - 1e-9) or np.any(v > self.upper[joints] + 1e-9):
            self.arm_status = int(P.ArmStatusCode.TARGET_BEYOND_LIMIT)
            return
        if self.arm_status == P.ArmStatusCode.TARGET_BEYOND_LIMIT:
            self.arm_status = int(P.ArmStatusCode.NORMAL)
        self.target[joints] = v

    def _on_GripperCtrl(self, f: P.GripperCtrl) -> None:
        if f.code in (P.GripperCode.ENABLE, P.GripperCode.ENABLE_CLEAR_ERROR):
            lo, hi = self.robot.gripper.width_range if self.robot.gripper else (0.0, 0.07)
            if not self.gripper_enabled:
                self.gripper_target = self.gripper
            self.gripper_enabled = True
            self.gripper_target = float(np.clip(f.width, lo, hi))
            self.gripper_effort = f.effort
        else:
            self.gripper_enabled = False
            self.gripper_effort = 0.0
        if f.set_zero:
            self.gripper = self.gripper_target = 0.0

    def _on_MotorEnable(self, f: P.MotorEnable) -> None:
        motors = list(range(6)) if f.motor in (7, 0xFF) else [f.motor - 1]
        if f.enable:
            newly = [m for m in motors if not self.enabled[m]]
            self.target[newly] = self.q[newly]
            self.qd[newly] = 0.0
        else:
            self.qd[motors] = 0.0
        self.enabled[motors] = f.enable

    def _on_MotorParamQuery(self, f: P.MotorParamQuery) -> list[P.Frame]:
        j = f.motor - 1
        if f.content == 1:
            return [P.MotorLimitsReply(f.motor, float(self.upper[j]), float(self.lower[j]), float(self.vmax[j]))]
        return [P.MotorMaxAccReply(f.motor, float(self.amax[j]))]

    def _on_ParamQuery(self, f: P.ParamQuery) -> list[P.Frame]:
        out: list[P.Frame] = []
        if f.query == 1:
            out.append(P.EndVelAccReply(*self.end_limits))
        elif f.query == 2:
            out.append(P.CollisionReply(self.collision_levels))
        elif f.query == 4:
            hi = self.robot.gripper.width_range[1] if self.robot.gripper else 0.07
            out.append(P.GripperTeachReply(100, round(hi, 3), 1))
        return out

    def _on_MotorLimitsConfig(self, f: P.MotorLimitsConfig) -> list[P.Frame]:
        j = f.motor - 1
        if f.max_angle is not None:
            self.upper[j] = f.max_angle
        if f.min_angle is not None:
            self.lower[j] = f.min_angle
        if f.max_speed is not None:
            self.vmax[j] = f.max_speed
        return [P.SettingReply(0x74, 0)]

    def _on_JointConfig(self, f: P.JointConfig) -> list[P.Frame]:
        joints = list(range(6)) if f.motor == 7 else [f.motor - 1]
        if f.apply_acc and f.max_acc is not None:
            self.amax[joints] = f.max_acc
        if f.clear_error and self.arm_status not in (P.ArmStatusCode.EMERGENCY_STOP,):
            self.arm_status = int(P.ArmStatusCode.NORMAL)
        return [P.SettingReply(0x75, 1 if f.set_zero else 0)]

    def _on_EndVelAccConfig(self, f: P.EndVelAccConfig) -> list[P.Frame]:
        self.end_limits = tuple(new if new is not None else old
                                for new, old in zip((f.linear_vel, f.angular_vel, f.linear_acc, f.angular_acc),
                                                    self.end_limits))
        return [P.SettingReply(0x79, 0)]

    def _on_CollisionConfig(self, f: P.CollisionConfig) -> list[P.Frame]:
        self.collision_levels = tuple(f.levels)
        return [P.SettingReply(0x7A, 0)]

    def _on_GripperTeachConfig(self, f: P.GripperTeachConfig) -> list[P.Frame]:
        return [P.SettingReply(0x7D, 0)]

    def _on_FirmwareData(self, f: P.FirmwareData) -> list[P.Frame]:
        text = self.config.firmware
        return [P.FirmwareData(text[i:i + 8]) for i in range(0, len(text), 8)]

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(message)

    # -- dynamics -------------------------------------------------------------------------------

    def play(self, t: np.ndarray, q: np.ndarray, gripper: np.ndarray | None = None) -> None:
        """Play a recorded trajectory from now on: ``t`` (N,) s (any origin, increasing),
        ``q`` (N, 6) rad, ``gripper`` (N,) m (default: the current width)."""
        t = np.asarray(t, dtype=np.float64)
        q = np.asarray(q, dtype=np.float64)
        if t.ndim != 1 or len(t) < 1 or q.shape != (len(t), 6):
            raise ValueError(f"playback needs t (N,) and q (N, 6), got {t.shape} and {q.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q)) and np.all(np.diff(t) > 0)):
            raise ValueError("playback t must be finite and strictly increasing, q finite")
        g = np.full(len(t), self.gripper) if gripper is None else np.asarray(gripper, dtype=np.float64)
        if g.shape != t.shape or not np.all(np.isfinite(g)):
            raise ValueError(f"playback gripper must be finite with shape {t.shape}, got {g.shape}")
        self.playback = Playback(t - t[0], q.copy(), g.copy(), start=self.time)

    def step(self, dt: float) -> None:
        """Advance the state by ``dt`` s."""
        self.time += dt
        if self.playback is not None:
            q, self.gripper = self.playback.at(self.time)
            self.qd = (q - self.q) / dt if dt > 0 else np.zeros(6)
            self.q = q
            return
        if self.following:
            tau = self.config.tau_s / (4.0 if self.mit_mode == P.MitMode.MIT else 1.0)
            step = (self.target - self.q) * (1.0 - math.exp(-dt / tau))
            cap = self.vmax * max(self.speed_pct, 1) / 100.0 * dt
            step = np.clip(step, -cap, cap)
            self.qd = step / dt if dt > 0 else np.zeros(6)
            self.q = self.q + step
        else:
            self.qd = np.zeros(6)
        if self.gripper_enabled and not self.estop:
            step = (self.gripper_target - self.gripper) * (1.0 - math.exp(-dt / self.config.tau_s))
            cap = self.config.gripper_speed * dt
            self.gripper += float(np.clip(step, -cap, cap))

    # -- feedback -------------------------------------------------------------------------------

    def flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Flange position (3,) m and roll-pitch-yaw (3,) rad (piper_sdk's FK and convention)."""
        T = np.eye(4)
        for origin, angle in zip(self._origins, self.q):
            c, s = math.cos(angle), math.sin(angle)
            rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
            T = T @ origin @ rz
        rpy = matrix_to_rpy(torch.from_numpy(T[:3, :3])).numpy()
        return T[:3, 3].copy(), rpy

    def feedback(self) -> list[P.Frame]:
        """One 5 ms cycle of feedback: 0x2A1..0x2A8, 0x251..0x256, and every fifth cycle
        0x261..0x266 (40 Hz)."""
        reached = bool(np.all(np.abs(self.target - self.q) < self.config.reached_tol))
        status = P.ArmStatus(self.ctrl_mode, self.arm_status, self.move_mode, 0, 0 if reached else 1, 0, 0)
        xyz, rpy = self.flange_pose()
        frames: list[P.Frame] = [status, P.EndPoseFeedback(0, xyz[0], xyz[1]), P.EndPoseFeedback(1, xyz[2], rpy[0]),
                                 P.EndPoseFeedback(2, rpy[1], rpy[2])]
        frames += [P.JointFeedback(p, self.q[2 * p], self.q[2 * p + 1]) for p in range(3)]
        grip_status = 0x40 if self.gripper_enabled else 0
        frames.append(P.GripperFeedback(self.gripper, self.gripper_effort if self.gripper_enabled else 0.0, grip_status))
        frames += [P.DriverHighSpeed(m + 1, float(np.clip(self.qd[m], -32.0, 32.0)), 0.0, self.q[m]) for m in range(6)]
        if self._tick % LOW_SPEED_DIVIDER == 0:
            c = self.config
            frames += [P.DriverLowSpeed(m + 1, c.voltage, c.temperature, c.temperature, 0x40 if self.enabled[m] else 0,
                                        0.0) for m in range(6)]
        self._tick += 1
        return frames

