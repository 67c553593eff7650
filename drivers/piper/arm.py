"""PiperArm: the PiPER over any python-can bus, with no SDK and no ROS.

    >>> with PiperArm.open("can0") as arm:             # socketcan, 1 Mbit/s
    ...     arm.enable()
    ...     arm.set_mode(speed_pct=30)
    ...     arm.move_joints([0, 0.5, -0.5, 0, 0, 0])
    ...     state = arm.wait_for_joint_state()

Reading: one :class:`can.Notifier` thread decodes every frame (:mod:`.protocol`) into a
:class:`~.feedback.FeedbackTracker`: the latest frame of every kind, complete joint samples
(:mod:`.assembler`), counts, rates, gaps, invalid frames, and the bus health; a monitor thread
logs health changes (20 Hz, like the SDK's watchdog). Optionally every frame, received and
sent, is written to a python-can log whose format follows the suffix (``.blf``, ``.asc``, ...).

Commands are checked before they are sent: joint targets against the robot model's limits
(NaN, wrong shapes and out-of-range values raise :class:`CommandError`), optional streaming
steps against its speed limits, the gripper against its range and 0..5 N*m.

Leaving safely (``close()`` / the context manager, also on an exception or Ctrl-C): if this
object commanded the arm and the arm is enabled, not e-stopped and its feedback is fresh, it
re-commands the measured joint position in MOVE J, so the arm stops and holds where it is. It
never sends disable (0x471 ``07 01``: the motors unpower and the arm falls) nor reset
(0x150 B0=2: power is cut, the arm drops) on its own. A read-only arm (recording, replay) sends
nothing at all.
"""

from __future__ import annotations

import copy
import logging
import math
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Sequence

import can
import numpy as np

from manisplat.drivers.base import ArmHealth, DriverError, JointState
from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.assembler import DEFAULT_WINDOW_S
from manisplat.drivers.piper.feedback import BusStats, FeedbackTracker, Received
from manisplat.drivers.replay import CanLogPlayer
from manisplat.robot import RobotModel, builtin_piper

log = logging.getLogger(__name__)

BITRATE = 1_000_000
ENABLE_RESEND_S = 0.01  # the SDK's EnablePiper() loop period


class PiperError(DriverError):
    """The arm did not do what was asked in time, or the bus failed."""


class CommandError(ValueError):
    """A command that must not be sent: NaN, wrong shape, outside the robot's limits."""


class _Tee(can.Listener):
    """A python-can log writer shared by the reader thread and senders (locked). A failing
    writer is logged and counted (``errors``), never raised into the reader thread."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._writer = can.Logger(self.path)
        self._lock = threading.Lock()
        self._closed = False
        self.errors = 0

    def on_message_received(self, msg: can.Message) -> None:
        channel = can.util.channel2int(msg.channel) if msg.channel is not None else None
        if channel is None or not 0 <= channel < 255:  # e.g. a virtual channel name: BLF needs a small int
            msg = copy.copy(msg)
            msg.channel = None
        with self._lock:
            if self._closed:
                return
            try:
                self._writer.on_message_received(msg)
            except Exception as exc:
                self.errors += 1
                if self.errors == 1:
                    log.error("PiperArm: writing %s failed (%r); later failures are only counted", self.path, exc)

    def stop(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._writer.stop()


class PiperArm:
    """A PiPER arm on a python-can bus. See the module docstring.

    Args:
        bus: any python-can bus (socketcan, slcan, gs_usb, pcan, virtual, ...).
        robot: the model whose limits commands are checked against (default: built-in PiPER).
        read_only: never send anything (recording, replay).
        log_path: write every frame received and sent to this python-can log (.blf, .asc, ...).
        window_s: joint-cycle window, s (:mod:`.assembler`).
        silence_timeout_s: feedback silence that makes the health ``silent``.
        own_bus: shut the bus down on :meth:`close` (set by :meth:`open`).
        on_health: called (from the monitor thread) with the new :class:`ArmHealth` on changes.
        on_joint_state: called (from the reader thread, keep it short) with every complete joint
            sample, e.g. to record all of them at the arm's rate.
    """

    def __init__(self, bus: can.BusABC, *, robot: RobotModel | None = None, read_only: bool = False,
                 log_path: str | Path | None = None, window_s: float = DEFAULT_WINDOW_S,
                 silence_timeout_s: float = 0.25, own_bus: bool = False,
                 on_health: Callable[[ArmHealth], None] | None = None,
                 on_joint_state: Callable[[JointState], None] | None = None) -> None:
        self.bus = bus
        self.robot = robot if robot is not None else builtin_piper(with_geometry=False)
        if self.robot.dof != 6:
            raise ValueError(f"PiperArm needs a 6-joint robot model, got {self.robot.dof} joints")
        self.read_only = read_only
        self.own_bus = own_bus
        self._tracker = FeedbackTracker(window_s, silence_timeout_s)
        self._cond = threading.Condition()
        self._on_health = on_health
        self._joint_listeners: list[Callable[[JointState], None]] = [on_joint_state] if on_joint_state else []
        self._commanded = False
        self._estopped = False
        self._speed_pct = 50
        self._last_target: tuple[np.ndarray, float] | None = None
        self._closed = False
        self._player: Any = None  # a CanLogPlayer this arm owns (open_log)
        self._tee = _Tee(log_path) if log_path is not None else None
        listeners: list[Any] = [self._Reader(self)]
        if self._tee is not None:
            listeners.append(self._tee)
        self._notifier = can.Notifier(bus, listeners, timeout=0.1)
        self._stop = threading.Event()
        self._health = ArmHealth("waiting", "no PiPER feedback received yet")
        self._monitor = threading.Thread(target=self._monitor_loop, name="PiperArm-monitor", daemon=True)
        self._monitor.start()

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def open(cls, channel: str = "can0", interface: str = "socketcan", bitrate: int = BITRATE,
             **kwargs: Any) -> PiperArm:
        """Open a bus and an arm on it (the arm shuts the bus down on close).

        Examples: ``PiperArm.open("can0")`` (socketcan; set the bitrate with ``ip link``),
        ``PiperArm.open("/dev/ttyACM0", "slcan")`` (serial adapters via pyserial),
        ``PiperArm.open("0", "gs_usb")``. ``kwargs`` split between the bus (anything
        :class:`can.Bus` takes) and the arm (``robot``, ``read_only``, ``log_path``, ...).
        """
        arm_keys = {"robot", "read_only", "log_path", "window_s", "silence_timeout_s", "on_health", "on_joint_state"}
        arm_kwargs = {k: kwargs.pop(k) for k in list(kwargs) if k in arm_keys}
        try:
            bus = can.Bus(channel=channel, interface=interface, bitrate=bitrate, **kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise PiperError(f"cannot open CAN {interface} {channel!r} at {bitrate} bit/s: {exc}") from exc
        return cls(bus, own_bus=True, **arm_kwargs)

    @classmethod
    def open_log(cls, path: str | Path, *, realtime: bool = True, speed: float = 1.0, **kwargs: Any) -> PiperArm:
        """A read-only arm reading a python-can log (.blf, .asc, .log, .csv, ...) replayed onto a
        private virtual bus (:class:`~manisplat.drivers.replay.CanLogPlayer`), with the recorded
        timing or as fast as possible. ``replay_done()`` tells when the log has been read."""
        player = CanLogPlayer(path, channel=f"piper-log-{uuid.uuid4().hex}", realtime=realtime, speed=speed)
        arm = cls(player.open_bus(), read_only=True, own_bus=True, **kwargs)
        arm._player = player
        player.start()
        return arm

    # -- reading ------------------------------------------------------------------------------

    class _Reader(can.Listener):
        def __init__(self, arm: PiperArm) -> None:
            self.arm = arm

        def on_message_received(self, msg: can.Message) -> None:
            arm = self.arm
            with arm._cond:
                sample = arm._tracker.ingest(msg, time.monotonic())
                arm._cond.notify_all()
            if sample is not None:
                for listener in arm._joint_listeners:
                    try:
                        listener(sample)
                    except Exception:
                        log.exception("PiperArm: on_joint_state listener failed")

        def on_error(self, exc: Exception) -> None:
            arm = self.arm
            with arm._cond:
                arm._tracker.note_read_error(exc, time.monotonic())
            if not arm._closed:
                log.error("PiperArm: CAN read failed: %s", exc)
                time.sleep(0.05)  # the notifier retries at once; do not spin on a dead bus

    def add_joint_listener(self, listener: Callable[[JointState], None]) -> None:
        """Call ``listener`` (from the reader thread) with every complete joint sample."""
        self._joint_listeners.append(listener)

    def add_listener(self, listener: can.Listener) -> None:
        """Give every received frame to ``listener`` too, on the reader thread (one Notifier per
        bus: several would split the frames between them). Keep ``on_message_received`` short."""
        self._notifier.add_listener(listener)

    def joint_state(self) -> JointState | None:
        """The latest complete joint sample (rad), or None before the first."""
        with self._cond:
            return self._tracker.joint_state()

    def wait_for_joint_state(self, after_seq: int = -1, timeout: float = 1.0) -> JointState:
        """The first joint sample with ``seq > after_seq``; :class:`TimeoutError` otherwise."""
        with self._cond:
            ok = self._cond.wait_for(lambda: (s := self._tracker.joint_state()) is not None and s.seq > after_seq,
                                     timeout)
            if not ok:
                raise TimeoutError(f"no joint sample after seq {after_seq} within {timeout} s "
                                   f"({self._tracker.health(time.monotonic()).detail or 'feedback flowing'})")
            return self._tracker.joint_state()

    def latest(self, can_id: int) -> Received[Any] | None:
        """The latest valid frame with ``can_id`` (e.g. ``P.CanId.ARM_STATUS``) with its times."""
        with self._cond:
            return self._tracker.latest(can_id)

    @property
    def status(self) -> P.ArmStatus | None:
        """The latest 0x2A1 arm status."""
        r = self.latest(P.CanId.ARM_STATUS)
        return r.frame if r else None

    @property
    def gripper_state(self) -> P.GripperFeedback | None:
        """The latest 0x2A8 gripper feedback."""
        r = self.latest(P.CanId.GRIPPER_FEEDBACK)
        return r.frame if r else None

    def motors_enabled(self, since_host: float = -math.inf) -> list[bool | None]:
        """Bit 6 of the latest 0x261..0x266 of each motor (None when none arrived after
        ``since_host``, a ``time.monotonic()`` value)."""
        out: list[bool | None] = []
        with self._cond:
            for motor in range(1, 7):
                r = self._tracker.latest(0x260 + motor)
                out.append(r.frame.enabled if r is not None and r.t_host > since_host else None)
        return out

    @property
    def tee_errors(self) -> int:
        """Frames the log tee failed to write (0 without a tee)."""
        return self._tee.errors if self._tee is not None else 0

    def stats(self) -> BusStats:
        """Frame counts, rates and gaps per ID, invalid frames, joint samples."""
        with self._cond:
            return self._tracker.stats()

    def health(self) -> ArmHealth:
        """Whether feedback flows (see :mod:`.feedback` for the states; ``ended`` once a replayed
        log has been read to its end)."""
        self._check_bus_state()
        with self._cond:
            h = self._tracker.health(time.monotonic())
            received = self._tracker.frames
        player = self._player
        if player is not None and player.done and received >= player.sent:
            detail = f"replay of {player.path} finished after {player.sent} frames"
            if player.error is not None:
                detail += f" (stopped early: {player.error})"
            return ArmHealth("ended", detail, h.silent_for_s)
        return h

    def wait_for_frames(self, count: int, timeout: float = 5.0) -> None:
        """Block until ``count`` frames have been received in total (TimeoutError otherwise)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._tracker.frames >= count, timeout):
                raise TimeoutError(f"received {self._tracker.frames} of {count} frames within {timeout} s")

    def replay_done(self, timeout: float | None = None) -> bool:
        """For :meth:`open_log`: wait until the whole log was sent and received here."""
        if self._player is None:
            raise PiperError("this arm does not read a log (use PiperArm.open_log)")
        if not self._player.wait(timeout):
            return False
        try:
            self.wait_for_frames(self._player.sent, timeout if timeout is not None else 60.0)
        except TimeoutError:
            return False
        return True

    def _check_bus_state(self) -> None:
        try:
            state = self.bus.state
        except (NotImplementedError, AttributeError, can.CanError):
            return
        if state == can.BusState.ERROR:
            with self._cond:
                self._tracker.note_bus_off(time.monotonic())

    def _monitor_loop(self) -> None:
        while not self._stop.wait(0.05):
            h = self.health()
            if h.state != self._health.state:
                level = logging.INFO if h.state in ("ok", "ended") else logging.WARNING
                log.log(level, "PiperArm: %s%s", h.state, f" ({h.detail})" if h.detail else "")
                self._health = h
                if self._on_health is not None:
                    try:
                        self._on_health(h)
                    except Exception:
                        log.exception("PiperArm: on_health callback failed")

    # -- commands -----------------------------------------------------------------------------

    def send(self, frame: P.Frame) -> None:
        """Send one protocol frame (validated by its encoder)."""
        if self.read_only:
            raise PiperError(f"read-only PiperArm: refusing to send {frame!r}")
        if self._closed:
            raise PiperError("PiperArm is closed")
        msg = P.to_message(frame)
        try:
            self.bus.send(msg, timeout=0.1)
        except can.CanError as exc:
            raise PiperError(f"sending {frame!r} failed: {exc}") from exc
        if self._tee is not None:
            msg.timestamp, msg.is_rx = time.time(), False
            self._tee.on_message_received(msg)

    def enable(self, timeout: float = 2.0) -> None:
        """Enable all six motors: send 0x471 ``07 02`` every 10 ms until every 0x261..0x266
        received after the first send reports bit 6 (driver enabled), as the SDK's
        ``EnablePiper()`` does. Raises :class:`PiperError` after ``timeout`` s."""
        start = time.monotonic()
        deadline = start + timeout
        self._commanded = True
        while True:
            self.send(P.MotorEnable(7, True))
            if all(self.motors_enabled(since_host=start)):
                self._estopped = False
                return
            if time.monotonic() > deadline:
                raise PiperError(f"the arm did not report all motors enabled within {timeout} s "
                                 f"(0x261..0x266 bit 6: {self.motors_enabled(since_host=start)}; "
                                 f"health: {self.health().state})")
            with self._cond:
                self._cond.wait(ENABLE_RESEND_S)

    def disable(self) -> None:
        """Unpower all motors (0x471 ``07 01``). The arm falls unless it rests on something."""
        log.warning("PiperArm: disabling the motors; an unsupported arm falls")
        self._commanded = True
        self.send(P.MotorEnable(7, False))

    def set_mode(self, ctrl_mode: P.CtrlMode = P.CtrlMode.CAN, move_mode: P.MoveMode = P.MoveMode.J,
                 speed_pct: int | None = None, mit_mode: P.MitMode = P.MitMode.POSITION_VELOCITY,
                 installation: int = 0) -> None:
        """Send 0x151: control mode (CAN), move mode (J), speed % of the arm's maximum (1..100,
        default: the last one set, initially 50), MIT flag."""
        speed = self._check_speed(speed_pct)
        self._commanded = True
        self.send(P.ModeCtrl(ctrl_mode, move_mode, speed, mit_mode, 0, installation))
        self._speed_pct = speed

    def move_joints(self, q: Sequence[float] | np.ndarray, speed_pct: int | None = None, *,
                    dt: float | None = None) -> None:
        """Command a joint target ``q`` (6,) rad in CAN control, MOVE J: 0x151 then 0x155..0x157,
        as the SDK does on every cycle. The arm's own planner moves there at ``speed_pct`` % of
        its speed.

        Args:
            speed_pct: 1..100 (default: the last one set).
            dt: when streaming, the time (s) this target follows the previous one: a step faster
                than the robot's speed limit x ``speed_pct`` on any joint is refused.
        """
        target = self.check_joint_target(q)
        speed = self._check_speed(speed_pct)
        if dt is not None and self._last_target is not None:
            self._check_step(target, dt, speed)
        self._commanded = True
        self.send(P.ModeCtrl(P.CtrlMode.CAN, P.MoveMode.J, speed, P.MitMode.POSITION_VELOCITY))
        for frame in P.joint_ctrl_frames(target):
            self.send(frame)
        self._speed_pct = speed
        self._last_target = (target, time.monotonic())

    def gripper(self, width_m: float, effort_nm: float = 1.0) -> None:
        """Open the gripper to ``width_m`` (finger-pad gap, m) with at most ``effort_nm`` N*m
        (0..5), enabling it (0x159 code 0x01)."""
        lo, hi = self.robot.gripper.width_range if self.robot.gripper else (0.0, 0.07)
        w, e = float(width_m), float(effort_nm)
        if not (math.isfinite(w) and lo <= w <= hi):
            raise CommandError(f"gripper width {width_m!r} m outside [{lo}, {hi}] m")
        if not (math.isfinite(e) and 0.0 <= e <= 5.0):
            raise CommandError(f"gripper effort {effort_nm!r} N*m outside [0, 5] N*m")
        self._commanded = True
        self.send(P.GripperCtrl(w, e, P.GripperCode.ENABLE))

    def estop(self) -> None:
        """Emergency stop (0x150 B0=1): the arm stops in a damped state and sinks slowly."""
        self._commanded = True
        self._estopped = True
        self.send(P.MotionCtrl1(P.EStop.STOP))

    def resume(self, timeout: float = 2.0) -> None:
        """Leave an e-stop: reset (0x150 B0=2) then enable (0x471, resent every 10 ms until all
        motors report enabled). The reset CUTS MOTOR POWER: the arm drops unless supported.
        Call :meth:`set_mode` afterwards."""
        log.warning("PiperArm: reset (0x150 B0=2) cuts motor power; the arm drops unless supported")
        self._commanded = True
        self.send(P.MotionCtrl1(P.EStop.RESUME))
        self._last_target = None
        for _ in range(2):  # the maintainer: enable at least twice after a reset (piper_sdk #66)
            self.send(P.MotorEnable(7, True))
            time.sleep(ENABLE_RESEND_S)
        self.enable(timeout)

    def hold(self, speed_pct: int = 10) -> bool:
        """Command the measured joint position (MOVE J) so the arm stops where it is. Returns
        False (and sends nothing) without fresh feedback."""
        with self._cond:
            state = self._tracker.joint_state()
            health = self._tracker.health(time.monotonic())
        if state is None or not health.ok:
            return False
        target = np.clip(state.q, self.robot.lower, self.robot.upper)
        self.send(P.ModeCtrl(P.CtrlMode.CAN, P.MoveMode.J, self._check_speed(speed_pct)))
        for frame in P.joint_ctrl_frames(target):
            self.send(frame)
        return True

    # -- checks -------------------------------------------------------------------------------

    def check_joint_target(self, q: Sequence[float] | np.ndarray) -> np.ndarray:
        """``q`` as a (6,) float64 array, or :class:`CommandError` (shape, NaN, limits)."""
        try:
            arr = np.asarray(q, dtype=np.float64)
        except (TypeError, ValueError):
            raise CommandError(f"joint target {q!r} is not a sequence of numbers") from None
        if arr.shape != (6,):
            raise CommandError(f"joint target must have shape (6,), got {arr.shape}")
        bad = ~np.isfinite(arr)
        if bad.any():
            raise CommandError(f"joint target has non-finite values at joints {list(np.flatnonzero(bad) + 1)}: {arr}")
        lo, hi = self.robot.lower, self.robot.upper
        out = np.flatnonzero((arr < lo - 1e-9) | (arr > hi + 1e-9))
        if out.size:
            parts = [f"joint{i + 1} {np.degrees(arr[i]):.3f} deg not in [{np.degrees(lo[i]):.3f}, "
                     f"{np.degrees(hi[i]):.3f}]" for i in out]
            raise CommandError("joint target outside the robot's limits: " + "; ".join(parts))
        return arr

    def _check_speed(self, speed_pct: int | None) -> int:
        speed = self._speed_pct if speed_pct is None else speed_pct
        if isinstance(speed, bool) or not isinstance(speed, (int, np.integer)) or not 1 <= speed <= 100:
            raise CommandError(f"speed_pct must be an int in 1..100, got {speed_pct!r}")
        return int(speed)

    def _check_step(self, target: np.ndarray, dt: float, speed: int) -> None:
        if not (math.isfinite(dt) and dt > 0):
            raise CommandError(f"dt must be > 0 s, got {dt!r}")
        previous = self._last_target[0]
        vmax = self.robot.velocity_limits * speed / 100.0
        v = np.abs(target - previous) / dt
        over = np.flatnonzero(v > vmax * (1 + 1e-9))
        if over.size:
            parts = [f"joint{i + 1} {v[i]:.3f} rad/s > {vmax[i]:.3f}" for i in over]
            raise CommandError(f"joint step over {dt} s exceeds the speed limit x {speed} %: " + "; ".join(parts))

    # -- lifetime -----------------------------------------------------------------------------

    def close(self) -> None:
        """Leave the arm safe (module docstring), stop reading, close the log and owned bus."""
        if self._closed:
            return
        try:
            if self._commanded and not self.read_only and not self._estopped:
                if not all(self.motors_enabled()):
                    log.info("PiperArm: closing; the motors are not all reported enabled, nothing to hold")
                elif self.hold():
                    log.info("PiperArm: holding the measured position on close")
                else:
                    log.warning("PiperArm: closing without fresh feedback; the arm keeps its last target")
        finally:
            self._closed = True
            self._stop.set()
            self._monitor.join(timeout=1.0)
            if self._player is not None:
                self._player.stop()
            self._notifier.stop(timeout=2.0)  # also stops the tee writer
            if self.own_bus:
                self.bus.shutdown()

    def __enter__(self) -> PiperArm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"PiperArm({self.bus.channel_info!r}, read_only={self.read_only}, health={self.health().state!r})"


