"""One arm's side of a recording: its joint samples, gripper frames, leader commands and CAN log,
on the recording's monotonic timeline.

An :class:`ArmFeed` listens to one :class:`~manisplat.drivers.piper.PiperArm` from before the
first episode to the end of the session: every complete joint sample is mapped onto the
monotonic timeline (the shared :class:`~.clock.ClockMap`) and kept for sync
(:class:`~.sync.JointHistory`); while an episode is active (:meth:`ArmFeed.activate`) the samples
also go to its joint stream. :meth:`ArmFeed.sync` gives the arm's state at a frame time. A
recorder has one feed per arm: ``joints.csv`` for the one arm of a version 1 episode (``name``
None), ``joints_<name>.csv`` for a named arm.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from manisplat.drivers.base import DriverError, JointState
from manisplat.drivers.piper import PiperArm
from manisplat.recorder.actions import LeaderCommands
from manisplat.recorder.canlog import CanLogSink
from manisplat.recorder.clock import Clock, ClockMap
from manisplat.recorder.gripper import GripperStream
from manisplat.recorder.sync import JointHistory
from manisplat.recorder.writer import EpisodeSink

WALL_STAMP_TOLERANCE_S = 5.0  # CAN stamps further than this from the wall clock are not wall-clock stamps
JOINT_TAIL_S = 0.1
"""s: an episode's joints.csv goes on this far past its end (20 samples at 200 Hz: the last frame's
state is bracketed), however long its frames then take to be matched."""


class _Active:
    """The episode an arm's joint samples go to, as the reader thread sees it."""

    def __init__(self, t0: float, sink: EpisodeSink, arm: str | None) -> None:
        self.t0 = t0
        self.sink = sink
        self.arm = arm
        self.last_joint_t = -math.inf
        self.joint_samples = 0
        self.until = math.inf  # monotonic s: later samples are not the episode's

    def add_joint(self, t: float, q: np.ndarray, gripper: float) -> None:
        if self.last_joint_t < t <= self.until:
            self.last_joint_t = t
            self.joint_samples += 1
            self.sink.put_joint(t - self.t0, q, gripper, self.arm)


class ArmFeed:
    """Everything a recorder keeps of one arm; see the module docstring.

    Args:
        arm: a PiperArm (read-only is enough) on its bus.
        clock: the host clocks.
        clock_map: the recording's wall-to-monotonic mapping (shared by every arm).
        max_action_age_s: a leader command older than this at a frame is stale, s.
        name: the arm's name in a version 2 episode (``joints_<name>.csv``), None for version 1.
    """

    def __init__(self, arm: PiperArm, clock: Clock, clock_map: ClockMap, max_action_age_s: float,
                 name: str | None = None) -> None:
        self.arm = arm
        self.clock = clock
        self.clock_map = clock_map
        self.name = name
        self.history = JointHistory()
        self.can_stamps = "wall"  # or "host" when the interface's stamps are not on the wall clock
        self.leader = LeaderCommands(self._can_to_mono, max_action_age_s)
        self.gripper = GripperStream(self._can_to_mono)
        self.can_log = CanLogSink()
        self.rejected_samples = 0
        self._active: _Active | None = None
        self._lock = threading.Lock()
        arm.add_joint_listener(self._on_joint)
        arm.add_listener(self.leader)
        arm.add_listener(self.gripper)
        arm.add_listener(self.can_log)

    @property
    def label(self) -> str:
        """How messages name the arm: ``"the arm"`` or ``"arm left"``."""
        return "the arm" if self.name is None else f"arm {self.name}"

    # -- the reader thread's side --------------------------------------------------------------

    def _can_to_mono(self, t: float) -> float:
        """A CAN frame's stamp on the monotonic timeline (wall-clock stamps; see wait)."""
        if self.can_stamps == "host":
            return self.clock.monotonic()
        return self.clock_map.to_mono(t)

    def _on_joint(self, state: JointState) -> None:
        t = state.t_host if self.can_stamps == "host" else self.clock_map.to_mono(state.t)
        if not math.isfinite(state.gripper):  # before the first gripper frame: not a full state
            self.rejected_samples += 1
            return
        with self._lock:
            if not self.history.append(t, np.append(state.q, state.gripper)):
                self.rejected_samples += 1
                return
            active = self._active
            if active is not None and t >= active.t0:
                active.add_joint(t, state.q, state.gripper)

    # -- episodes -----------------------------------------------------------------------------

    def activate(self, t0: float, sink: EpisodeSink, until: float = math.inf) -> None:
        """Send joint samples at or after ``t0`` and not after ``until`` (monotonic s) to ``sink``,
        starting with those already received (the set-up takes a few ms)."""
        active = _Active(t0, sink, self.name)
        active.until = until
        with self._lock:
            self._active = active
            times, values = self.history.since(t0)
            for t, v in zip(times, values):
                active.add_joint(float(t), v[:6], float(v[6]))

    def end_at(self, t: float) -> None:
        """Send no joint sample stamped after ``t`` (monotonic s) to the episode: it has ended,
        and the recorder may go on a while to match its last frames."""
        with self._lock:
            if self._active is not None:
                self._active.until = min(self._active.until, t)

    def deactivate(self) -> int:
        """Stop sending joint samples to the episode; returns how many it got."""
        with self._lock:
            active, self._active = self._active, None
        return 0 if active is None else active.joint_samples

    # -- set-up and sync ----------------------------------------------------------------------

    def wait(self, timeout: float = 3.0) -> str | None:
        """Wait for complete joint samples (with the gripper) and check the CAN stamps' clock.

        Raises DriverError when none comes within ``timeout`` (real) s. CAN stamps more than
        5 s away from the wall clock (an interface with its own time base) are replaced by the
        host arrival times; then returns the warning to give (None otherwise).
        """
        try:
            state = self.arm.wait_for_joint_state(timeout=timeout)
            while not math.isfinite(state.gripper):
                state = self.arm.wait_for_joint_state(state.seq, timeout=timeout)
        except TimeoutError as exc:
            which = "" if self.name is None else f"arm {self.name}: "
            raise DriverError(f"{which}no PiPER joint feedback within {timeout} s "
                              f"({self.arm.health().detail or exc}); check power, wiring, the bitrate (1 Mbit/s) "
                              "and that the arm is not a silent leader") from None
        warning = None
        skew = state.t - self.clock.wall()
        if abs(skew) > WALL_STAMP_TOLERANCE_S and self.can_stamps == "wall":
            with self._lock:
                self.can_stamps = "host"
                for history in (self.history, self.gripper.history, self.leader.joints, self.leader.gripper):
                    history.clear()  # mapped from the wrong clock
            whose = "" if self.name is None else f" of arm {self.name}"
            warning = (f"the CAN interface's timestamps{whose} are {skew:.1f} s away from the wall clock "
                       "(not SocketCAN-style wall stamps); using the host arrival time of each joint sample instead")
        while self.history.last_t is None or self.gripper.history.last_t is None:
            latest = self.arm.joint_state()
            self.arm.wait_for_joint_state(latest.seq if latest else -1, timeout=timeout)
        return warning

    def describe_stamps(self) -> str:
        """What the arm's joint times are, for ``episode.json``."""
        return ("bus stamps (wall clock), mapped with the measured offset" if self.can_stamps == "wall"
                else "host arrival time (monotonic)")

    def known_at(self, t: float) -> bool:
        """Whether a joint sample and a gripper frame at or after ``t`` (monotonic s) have arrived."""
        joints_last, gripper_last = self.history.last_t, self.gripper.history.last_t
        return joints_last is not None and gripper_last is not None and min(joints_last, gripper_last) >= t

    def sync(self, t: float, max_gap_s: float) -> tuple[np.ndarray, float, int, float]:
        """The arm's state at ``t`` (monotonic s): (7,) q1..q6 rad and the gripper m from its own
        frames (:mod:`.gripper`), the gap interpolated across (s), the sync flags and the gripper's
        effort (N*m, from the same frames)."""
        values, gap, flags = self.history.sync(t, max_gap_s)
        gripper, gripper_gap, gripper_flags = self.gripper.history.sync(t, max_gap_s)
        values[6] = gripper[0]
        return values, max(gap, gripper_gap), flags | gripper_flags, float(gripper[1])
