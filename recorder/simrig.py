"""A simulated PiPER (and optionally a simulated leader arm) on a private python-can virtual
bus, run on a :class:`~.clock.Clock`: the hardware side of ``manisplat-record --sim``, of the
recorder's tests and of its benchmarks.

Motions:
* ``"wave"``: the arm plays a smooth trajectory (slow sines around a mid pose) as its state, so
  its true state at any time is known exactly (:meth:`SimRig.truth`);
* ``"teleop"``: a simulated leader arm sends MOVE J commands (0x151, 0x155..0x157, 0x159) at the
  feedback rate on the same bus, the simulated follower is enabled and follows them through its
  own dynamics (a lag), as a PiPER leader/follower pair does;
* ``"still"``: the arm stands at ``q0``.

Frames carry the simulated time as timestamp on the wall clock of ``clock``
(``clock.wall()`` at model time 0 + model time), so a recorder maps them as it maps SocketCAN
stamps. With a :class:`~.clock.ManualClock` the rig runs lock-step (``lockstep=True``): it
advances the clock cycle by cycle, lets the consumers (a PiperArm, a camera) catch up, and never
depends on the machine's speed; otherwise it follows the clock in real (or scaled) time.
:meth:`silence` makes the bus go quiet for a while (the arm keeps moving).
"""

from __future__ import annotations

import logging
import math
import threading
import uuid
from typing import Callable

import can
import numpy as np

from manisplat.drivers.piper import SimConfig, SimulatedPiper
from manisplat.drivers.piper import protocol as P
from manisplat.recorder.clock import Clock, ManualClock

log = logging.getLogger(__name__)

FRAME_S = 130e-6  # one frame at 1 Mbit/s
MOTIONS = ("wave", "teleop", "still")
WAVE_AMPLITUDE = np.radians([25.0, 15.0, 15.0, 20.0, 15.0, 25.0])
WAVE_PERIOD_S = np.array([7.0, 9.0, 8.0, 6.0, 7.5, 5.0])
WAVE_MID = np.array([0.0, math.radians(45), math.radians(-45), 0.0, 0.0, 0.0])


def wave_state(s: np.ndarray | float) -> np.ndarray:
    """The demo motion at times ``s`` (N,) s: (N, 7) q1..q6 rad and gripper m. Each joint is a
    sine (amplitude 15-25 deg, period 5-9 s, at most 31 deg/s) around a mid pose (J2 45 deg,
    J3 -45 deg), inside the PiPER's limits; the gripper opens and closes (5-65 mm, 6 s)."""
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))[:, None]
    q = WAVE_MID + WAVE_AMPLITUDE * np.sin(2 * np.pi * s / WAVE_PERIOD_S)
    gripper = 0.035 + 0.03 * np.sin(2 * np.pi * s / 6.0)
    return np.concatenate([q, gripper], axis=1)


def wave_gripper_effort(s: np.ndarray | float) -> np.ndarray:
    """The gripper effort (N, ) N*m the demo motion reports at times ``s`` (N,) s: 0.2-1.8 N*m,
    pressing hardest where the gripper is narrowest."""
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))
    return 1.0 - 0.8 * np.sin(2 * np.pi * s / 6.0)


class SimRig:
    """The simulated hardware on its own virtual channel. See the module docstring.

    Args:
        clock: the clock to run on (a :class:`ManualClock` runs lock-step).
        motion: ``"wave"``, ``"teleop"`` or ``"still"``.
        q0: initial joints for ``"still"`` (rad).
        lockstep_batch: cycles between waits for the consumers in lock-step.
        max_lead_s: in lock-step, how far the clock may run ahead of ``consumer_time()``.
        keep_states: keep every simulated state for :meth:`truth` (teleop/still; 60 B per cycle).
    """

    def __init__(self, clock: Clock, *, motion: str = "wave", q0: np.ndarray | None = None, lockstep_batch: int = 4,
                 max_lead_s: float = 0.1, keep_states: bool = True) -> None:
        if motion not in MOTIONS:
            raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
        self.clock = clock
        self.motion = motion
        self.channel = f"manisplat-sim-{uuid.uuid4().hex}-bus"
        self.lockstep = isinstance(clock, ManualClock)
        self.lockstep_batch = lockstep_batch
        self.max_lead_s = max_lead_s
        self._bus = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=True)
        self.m0 = clock.monotonic()
        self.t0_wall = clock.wall()
        config = SimConfig(q0=q0) if q0 is not None else SimConfig()
        self.sim = SimulatedPiper(self._bus, config=config, t0=self.t0_wall)
        self._leader_bus: can.BusABC | None = None
        if motion in ("wave", "teleop"):
            with self.sim._lock:  # start where the motion starts
                start = wave_state(0.0)[0]
                self.sim.model.q = start[:6].copy()
                self.sim.model.target = start[:6].copy()
                self.sim.model.gripper = self.sim.model.gripper_target = float(start[6])
        if motion == "teleop":
            self._leader_bus = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=True)
        self.leader_frames_sent = 0
        self.keep_states = keep_states
        self._consumers: list[Callable[[int], None]] = []
        self._consumer_time: Callable[[], float] | None = None
        self._silences: list[tuple[float, float]] = []
        self._states_t: list[float] = []
        self._states_v: list[np.ndarray] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.cycles = 0
        self.late_cycles = 0
        self.frames_sent = 0
        self.error: BaseException | None = None

    # -- wiring -------------------------------------------------------------------------------

    def open_bus(self) -> can.BusABC:
        """A bus on the rig's channel for a consumer (a PiperArm)."""
        return can.Bus(interface="virtual", channel=self.channel)

    def add_consumer(self, wait_for_frames: Callable[[int], None]) -> None:
        """In lock-step, call ``wait_for_frames(n)`` (e.g. ``PiperArm.wait_for_frames``) with the
        number of frames sent so far before the clock moves on."""
        self._consumers.append(wait_for_frames)

    def follow(self, consumer_time: Callable[[], float]) -> None:
        """In lock-step, keep the clock within ``max_lead_s`` of ``consumer_time()`` (e.g. the
        due time of the last frame a replayed camera delivered)."""
        self._consumer_time = consumer_time

    def silence(self, start: float, end: float) -> None:
        """No frame on the bus for monotonic times in ``[start, end)`` (the arm keeps moving)."""
        self._silences.append((start, end))

    # -- running ------------------------------------------------------------------------------

    def start(self) -> SimRig:
        self._thread = threading.Thread(target=self._run, name="SimRig", daemon=True)
        self._thread.start()
        return self

    def _silent(self, t: float) -> bool:
        return any(a <= t < b for a, b in self._silences)

    def _run(self) -> None:
        period = self.sim.period
        try:
            while not self._stop.is_set():
                t_next = self.m0 + (self.cycles + 1) * period
                if self.lockstep:
                    self._wait_for_consumers(t_next)
                    self.clock.advance_to(t_next)
                elif not self.clock.sleep_until(t_next, self._stop):
                    break
                elif self.clock.monotonic() - t_next > 10 * period:
                    self.late_cycles += 1
                self._cycle(t_next)
        except BaseException as exc:  # report, do not die silently
            self.error = exc
            log.exception("SimRig: stopped by an error")

    def _cycle(self, t: float) -> None:
        if self.motion == "wave":  # the state the arm reports after this cycle
            state = wave_state(t - self.m0)[0]
            with self.sim._lock:
                self.sim.model.q = state[:6].copy()
                self.sim.model.gripper = self.sim.model.gripper_target = float(state[6])  # enabled, where it is
                self.sim.model.gripper_enabled = True
                self.sim.model.gripper_effort = float(wave_gripper_effort(t - self.m0)[0])
        if self._silent(t):
            with self.sim._lock:
                self.sim.model.step(self.sim.period)
        else:
            if self._leader_bus is not None:
                self._send_leader(t - self.sim.period)
            self.sim.step()
        self.cycles += 1
        self.frames_sent = self.sim.frames_sent + self.leader_frames_sent
        if self.keep_states and self.motion != "wave":
            state = self.sim.state()
            self._states_t.append(t)
            self._states_v.append(np.append(state["q"], state["gripper"]))

    def _send_leader(self, t: float) -> None:
        """The leader's commands of the cycle starting at ``t`` (stamped then)."""
        s = t - self.m0
        cmd = wave_state(s)[0]
        stamp = self.t0_wall + s
        frames: list[P.Frame] = []
        if self.cycles == 0:
            frames.append(P.MotorEnable(7, True))
        frames += [P.ModeCtrl(P.CtrlMode.CAN, P.MoveMode.J, 100), *P.joint_ctrl_frames(cmd[:6]),
                   P.GripperCtrl(float(cmd[6]), 1.0, P.GripperCode.ENABLE)]
        for i, frame in enumerate(frames):
            self._leader_bus.send(P.to_message(frame, timestamp=stamp + i * FRAME_S))
        self.leader_frames_sent += len(frames)

    def _wait_for_consumers(self, t_next: float) -> None:
        if self.cycles % self.lockstep_batch == 0:
            sent = self.sim.frames_sent + self.leader_frames_sent
            for wait in self._consumers:
                wait(sent)
        if self._consumer_time is not None:
            while not self._stop.is_set() and t_next - self._consumer_time() > self.max_lead_s:
                self._stop.wait(0.0005)

    def stop(self) -> None:
        """Stop the thread and close the rig's buses."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._bus.shutdown()
        if self._leader_bus is not None:
            self._leader_bus.shutdown()

    def __enter__(self) -> SimRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- truth --------------------------------------------------------------------------------

    def truth(self, t: np.ndarray) -> np.ndarray:
        """The arm's true state (N, 7) (q1..q6 rad, gripper m) at monotonic times ``t`` (N,):
        exact for ``"wave"`` (the analytic motion), else interpolated between the simulated
        cycles (``keep_states``)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        if self.motion == "wave":
            return wave_state(t - self.m0)
        if not self._states_t:
            raise ValueError("no simulated state kept (keep_states=False or no cycle ran)")
        times = np.asarray(self._states_t)
        values = np.asarray(self._states_v)
        return np.stack([np.interp(t, times, values[:, j]) for j in range(7)], axis=1)

    def leader_command(self, t: np.ndarray) -> np.ndarray:
        """The leader's command (N, 7) in effect at monotonic times ``t``: the latest whose
        0x155 frame (sent at the start of a cycle, after 0x151; after 0x471 too on the first
        cycle, frames 130 us apart) is stamped at or before ``t``."""
        if self.motion != "teleop":
            raise ValueError("the rig has no leader arm (motion is not 'teleop')")
        period = self.sim.period
        s = np.atleast_1d(np.asarray(t, dtype=np.float64)) - self.m0
        j = np.floor((s - FRAME_S) / period + 1e-12)
        j = np.where((j == 0) & (s < 2 * FRAME_S), -1, j)
        if np.any(j < 0):
            raise ValueError("a time before the leader's first command")
        return wave_state(j * period)
